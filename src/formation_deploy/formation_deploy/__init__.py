"""Deployment helpers: the docker compose generator (``formation-compose``)."""
