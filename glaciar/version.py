"""The version of glaciar: a leaf, so that modules that stamp it on what they write do not
import the package (whose ``__init__`` reaches them)."""

__version__ = "0.1.0"
