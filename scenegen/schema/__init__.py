"""Pydantic models: the language between stages (condition, proposals, checks, records)."""
