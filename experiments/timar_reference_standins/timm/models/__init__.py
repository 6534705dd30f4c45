"""Stand-in package: only ``timm.models.vision_transformer.Block``."""
