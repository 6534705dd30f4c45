"""Minimal stand-in for the parts of timm the public TIMAR code imports (see vision_transformer.py)."""
