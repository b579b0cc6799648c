"""ilt: inverse light transport (Seitz, Matsushita & Kutulakos, ICCV 2005)."""

__version__ = "0.1.0"
