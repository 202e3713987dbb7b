"""2D supervision: masks, physical scales, image-text embeddings and their PCA space."""
