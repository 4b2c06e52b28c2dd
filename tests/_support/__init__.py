"""Helpers shared by the test files: seeded random models and MJCF trees, jaxpr equation counts."""
