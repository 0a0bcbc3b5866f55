"""Render orchestration, the sensor model, HDF5 shards, RefineNet patches and inspection."""
