"""Sizes more than one layer agrees on.

A library entry must be describable as a query would be, so the least number of occupied voxels
a query needs is also the least a library model may have; both read it here.
"""

# Occupied voxels a query (and a library model) needs: fewer leave too little to describe.
MIN_VOXELS = 50
