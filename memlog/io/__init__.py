"""memlog.io."""
