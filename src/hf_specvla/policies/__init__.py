"""Policies: the Meta-World VLA as transformers splits a model (configuration, processing, modeling). A policy
imports no simulator, training or CLI code."""

from .._lazy import lazy_exports

__all__ = ["PRESETS", "POLICY_CONFIG_NAME", "DecodingMethod", "VLAPolicy", "VLAPolicyConfig", "VLAProcessor"]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".configuration_vla": ("POLICY_CONFIG_NAME", "VLAPolicyConfig"),
        ".processing_vla": ("VLAProcessor",),
        ".modeling_vla": ("VLAPolicy",),
        ".decoding_methods": ("DecodingMethod", "PRESETS"),
    },
    globals(),
)
