"""Aerial scene data: synthetic cities, webdataset shards, converters, view sampling and batching."""

from anycity.data.schema import SCHEMA_VERSION, SceneRecord, ViewRecord
from anycity.data.writer import ShardSetWriter, read_index, shard_urls, split_scenes

__all__ = ["SCHEMA_VERSION", "SceneRecord", "ViewRecord", "ShardSetWriter", "read_index", "shard_urls",
           "split_scenes"]
