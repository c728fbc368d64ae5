"""Synthetic RGB-D datasets in BOP format from the simulated workcell (``posegrasp datagen``)."""
