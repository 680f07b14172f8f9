"""Alembic environment and versions: the only thing that creates or changes the database schema."""
