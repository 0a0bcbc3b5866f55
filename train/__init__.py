"""Datasets over shards, augmentation, and the ChArUcoNet / RefineNet trainers."""
