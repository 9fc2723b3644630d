"""Preparing a query: validation, its own frame, the ways up it may stand, and the floor and
detached clusters set aside."""
