"""Physical constants: the one copy (CODATA 2018 exact values, SI units)."""

#: Speed of light in vacuum (m/s).  Ranges are 0.5 c t of the round-trip time everywhere.
SPEED_OF_LIGHT_M_S = 299_792_458.0
#: Planck constant (J s).
H_PLANCK_J_S = 6.62607015e-34
#: Elementary charge (C).
Q_ELECTRON_C = 1.602176634e-19
