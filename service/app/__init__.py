"""The networked mapping service: Zenoh ingest, sessions, durable store, pose fan-out, HTTP API."""
