"""Fixtures that start the real services the distributed tests run against."""
