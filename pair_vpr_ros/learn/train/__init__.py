"""Training of both Pair-VPR stages (`stage1`, `stage2`), single process or under torchrun."""
