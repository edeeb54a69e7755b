"""memlog.localize."""
