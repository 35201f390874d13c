"""thermocomp, the application: the ``thermocomp`` command and the compensation runtime.

The top layer: it may import :mod:`calibration`, :mod:`cnc_adapters` and :mod:`compensator`;
none of them imports it. See ``docs/ARCHITECTURE.md``.
"""

__version__ = "0.1.0"
