"""robot_client (placeholder public API; filled in by its issue)."""
