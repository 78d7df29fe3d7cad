"""Constants and helpers shared by the tests (imported as ``from support import ...``)."""

# One absolute start stamp for every synthetic recording: EuRoC-like (whole seconds, > 2**53 ns, so a float64
# round trip of a stamp would lose nanoseconds and a test would see it).
T0 = 1_403_636_579_000_000_000
