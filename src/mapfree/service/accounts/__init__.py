"""Accounts: API tokens and browser sessions, their lineage, the storage quota."""
