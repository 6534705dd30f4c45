"""Mesh geometry: operators for DiffusionNet (Laplacian, mass, eigenbasis, gradients, disk cache),
the DiffusionNet layers, and topology variants of a face mesh with exact maps to the base surface.

Submodules are imported explicitly so that ``import jaxtalk.geometry`` stays cheap.
"""
