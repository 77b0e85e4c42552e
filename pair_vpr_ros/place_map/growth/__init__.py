"""What lets a map grow with places and appearances, not with hours (docs/map-storage.md,
growth): tables.py (the keyframe store's `signatures`, `links` and `represented` tables, each
row with its CRC32), compact.py (`compact_map`: the policy and the dense codec applied to a
saved map, `pairvpr-map compact`)."""
