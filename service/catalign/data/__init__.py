"""Data for training and evaluation: shape sources, partial views and shape neighbours."""
