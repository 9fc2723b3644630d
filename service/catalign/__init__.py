"""catalign: category-level registration of partial point clouds against a CAD library.

The package is split by pipeline stage: ``geometry`` (I/O, sampling, SE(3), NCC), ``data``
(shape sources, partial views, shape neighbours), ``features`` (sparse convolution, ResUNet),
``training``, ``registration``, ``library``, ``evaluation`` and ``api``; ``cli`` is the
command-line front door.
"""

__version__ = "0.1.0"
