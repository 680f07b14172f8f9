"""Physical constants the science shares; importable without numpy (the command line's help uses them)."""

GRAVITY_M_S2 = 9.80665  # standard gravity (ISO 80000-3)
