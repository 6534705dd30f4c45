"""Data: the built-in SynthTalk corpus (``jaxtalk.data.synthtalk``), readers for published dataset
formats (``jaxtalk.data.formats``) and deterministic batching (``jaxtalk.data.batching``).

Submodules are imported explicitly so that ``import jaxtalk.data`` stays cheap.
"""
