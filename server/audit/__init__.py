"""Audit log: who read or changed which patient record, and who commanded motion."""
