"""Policies: the Meta-World VLA as transformers splits a model (configuration, processing, modeling), an OpenVLA
checkpoint as a policy, and the acting both share. A policy imports no simulator, training or CLI code."""

from .._lazy import lazy_exports

__all__ = [
    "PRESETS",
    "POLICY_CONFIG_NAME",
    "ActionPolicy",
    "DecodingMethod",
    "OpenVLAPolicy",
    "VLAPolicy",
    "VLAPolicyConfig",
    "VLAProcessor",
    "load_policy",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".configuration_vla": ("POLICY_CONFIG_NAME", "VLAPolicyConfig"),
        ".processing_vla": ("VLAProcessor",),
        ".modeling_vla": ("VLAPolicy",),
        ".acting": ("ActionPolicy",),
        ".openvla_policy": ("OpenVLAPolicy",),
        ".loading": ("load_policy",),
        ".decoding_methods": ("DecodingMethod", "PRESETS"),
    },
    globals(),
)
