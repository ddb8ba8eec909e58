"""Marionette: a world model pipeline for interactive games with articulated characters."""

__version__ = "0.1.0"
