"""Service-wide settings, errors and security."""
