"""Patient records; every read and change is written to the audit log."""
