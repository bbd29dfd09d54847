"""The simulator side: Meta-World envs, seed ranges, demonstrations, one rollout, evaluation and the paired
comparison. Submodules are imported by name (``hf_specvla.metaworld.env`` ...) so that reading a seed range does
not load MuJoCo."""
