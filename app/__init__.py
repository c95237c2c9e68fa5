"""fidotrack: marker-based camera tracking after Claus & Fitzgibbon (WACV 2005)."""

__version__ = "0.1.0"
