"""Gymnasium environments shipped with zenrl."""
