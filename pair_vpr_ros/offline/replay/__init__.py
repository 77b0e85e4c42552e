"""`pairvpr-bag-replay` and `build_map`: a bag or image folder through the pipeline."""
