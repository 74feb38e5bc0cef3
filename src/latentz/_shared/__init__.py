"""Helpers shared by every stage: validation at the API boundary and atomic output."""
