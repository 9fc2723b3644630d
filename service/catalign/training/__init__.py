"""Training: positive pairs (same-instance and NCC cross-instance), the loss and the loop."""
