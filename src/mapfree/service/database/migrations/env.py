"""Alembic environment: migrations run on the connection ``mapfree.service.database.migrations.upgrade`` passes in (its
transaction holds the database's migration lock), against the service's models."""

from alembic import context

from mapfree.service.database.models import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
