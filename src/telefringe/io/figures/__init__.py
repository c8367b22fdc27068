"""Figures written as files: one module per figure (PNG)."""
