"""The database: the schema (SQLAlchemy models), its migrations (Alembic) and backups."""
