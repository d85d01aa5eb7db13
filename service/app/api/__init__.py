"""The HTTP API (FastAPI): `create_app(runtime)` builds the application."""
