"""Meshes kept and built, with no HTTP in sight: the store (catalogue and files),
the parse pool, the build jobs, and levels and materials as a client fetches them."""
