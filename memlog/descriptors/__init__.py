"""memlog.descriptors."""
