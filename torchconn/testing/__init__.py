"""Independent reference implementations used by the tests and benchmarks (not by the pipeline).

- :func:`~torchconn.testing.numpy_swimmer.connection_and_metric_numpy` -- the N-link swimmer's
  ``A`` and ``M`` derived per shape in plain NumPy, a different route from the batched torch code.
"""

from .numpy_swimmer import connection_and_metric_numpy

__all__ = ["connection_and_metric_numpy"]
