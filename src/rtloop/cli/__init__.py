"""The ``rtloop`` commands."""
