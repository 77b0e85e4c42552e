"""The place map's index kind "milvus": a Milvus collection (milvus-lite file or server) as the
keyframe index: index.py (MilvusIndex), collection.py (connect, schema, version), expr.py
(filter expressions), fresh.py (rows not yet visible to the server's search), prune.py (rows
no saved map names; docs/milvus.md)."""
