"""The HTTP API: FastAPI app (``main.create_app``), routers in ``routes/``.

Routers only translate HTTP to calls on the store, the job runner and the
encoders (``export``, ``packets``); no geometry is done here.
"""
