"""memlog.models."""
