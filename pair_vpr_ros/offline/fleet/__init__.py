"""`pairvpr-fleet-replay`: several robots' bags replayed with the fleet exchange."""
