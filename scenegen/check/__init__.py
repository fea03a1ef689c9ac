"""Verification stages before physics: cheap geometric checks."""
