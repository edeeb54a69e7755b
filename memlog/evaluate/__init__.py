"""memlog.evaluate."""
