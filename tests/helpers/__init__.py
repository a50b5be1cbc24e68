"""What tests share: waiting for a condition, builders and fixtures used by more than one folder."""
