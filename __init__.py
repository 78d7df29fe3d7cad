"""uwbcal: robust online UWB anchor calibration from a robot's own pose estimate, as a logging-first offline
analysis pipeline (convert -> pipeline stages -> evaluate; ``uwbcal --help``)."""

__version__ = "0.1.0"
