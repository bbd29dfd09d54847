"""Policies: the Meta-World VLA (configuration + modeling). A policy imports no simulator, training or CLI code."""

from .._lazy import lazy_exports

__all__ = ["POLICY_CONFIG_NAME", "VLAPolicy", "VLAPolicyConfig"]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {".configuration_vla": ("POLICY_CONFIG_NAME", "VLAPolicyConfig"), ".modeling_vla": ("VLAPolicy",)},
    globals(),
)
