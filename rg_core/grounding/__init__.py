"""Grounding: queries -> 3D Gaussian groups, boxes, explanations and masks (the paper's LVLM-guided
hierarchical grouping)."""
