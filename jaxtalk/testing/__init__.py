"""Tools for testing and measuring jaxtalk's own pipelines, shipped like ``numpy.testing``: the
test suite and the experiments use them, and so can a user checking a pipeline on their own faces.

* :mod:`~jaxtalk.testing.faces`: face meshes of the kinds people bring, with known semantic points
  (the alignment tests' and ``experiments/canonical_alignment.py``'s gallery).
"""
