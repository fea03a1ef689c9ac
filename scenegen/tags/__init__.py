"""Stage tag: rare-case predicates measured on the settled scene (predicates.py; docs/tags.md)."""
