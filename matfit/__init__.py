"""matfit: photorealistic principled-BSDF parameters from an edited picture of a material (see README.md)."""
