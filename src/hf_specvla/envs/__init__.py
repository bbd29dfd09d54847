"""Simulated environments to validate policies on (Meta-World)."""
