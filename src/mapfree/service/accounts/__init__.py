"""Accounts: API tokens and browser sessions, their lineage, who is calling a request, the quotas (storage, and
test evaluations per day)."""
