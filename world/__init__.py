"""The sample and the instrument: scenes, the simulated AFM, identification."""
