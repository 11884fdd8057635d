"""Datasets: manifests, readers for the on-disk formats, the torch Dataset and samplers."""
