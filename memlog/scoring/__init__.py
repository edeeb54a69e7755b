"""memlog.scoring."""
