"""Data layer: spacecraft mesh processing, dataset writer and reader."""
