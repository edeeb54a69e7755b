"""memlog.selection."""
