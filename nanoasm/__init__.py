"""nanoasm: automated AFM nanoassembly.

The packages ``nanoasm.cad`` (layouts), ``nanoasm.world`` (scenes, the simulated AFM,
identification), ``nanoasm.planner``, ``nanoasm.drift`` and ``nanoasm.executor`` live in
the repository's top-level folders of the same names.
"""

__version__ = "0.1.0"
