"""The REST API: routers under ``/api``."""
