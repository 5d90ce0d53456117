"""vision_server (placeholder public API; filled in by its issue)."""
