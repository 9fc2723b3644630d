"""The decision: which refined pose is the answer, its alternatives, its evidence and
confidence."""
