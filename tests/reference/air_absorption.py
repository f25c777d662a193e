"""Air absorption from its physics, for checking `acoustic_sim.air.air_absorption_db_per_m`.

ISO 9613-1 (annex A) condenses three terms into fitted constants: classical (viscosity and heat
conduction) absorption and one relaxation process each for oxygen and nitrogen. Here the
relaxation terms are built from first principles instead: each process absorbs, per wavelength,

    alpha * lambda = 2 (alpha lambda)_max (f / f_r) / (1 + (f / f_r)^2),
    (alpha lambda)_max = (2 pi / 35) X (theta / T)^2 exp(-theta / T),

with the gas's mole fraction X in air and its characteristic vibrational temperature theta, and
the wavelength c(T) / f from the ideal-gas speed of sound. The water vapour content comes from
Buck's (1981) saturation vapour pressure, not the standard's formula. Only the relaxation
frequencies f_r (empirical fits to measurements) and the classical coefficient are the
standard's own. The two agree within about 0.1 % (the rounding of the standard's constants).
"""

import numpy as np

OXYGEN = (0.209, 2239.1)  # mole fraction, vibrational temperature [K]
NITROGEN = (0.781, 3352.0)
T_REF, P_REF = 293.15, 101.325  # [K], [kPa]
SPEED_AT_T_REF = 343.2  # [m/s] at 20 C, dry air
NEPER_TO_DB = 20.0 / np.log(10.0)


def saturation_vapour_pressure_kpa(temperature_c: float) -> float:
    """Buck (1981), over water."""
    return 0.61121 * np.exp((18.678 - temperature_c / 234.5) * (temperature_c / (257.14 + temperature_c)))


def air_absorption_db_per_m(frequency_hz, temperature_c=20.0, relative_humidity=50.0, pressure_kpa=101.325):
    f = np.asarray(frequency_hz, dtype=np.float64)
    t = temperature_c + 273.15
    p = pressure_kpa / P_REF
    vapour_percent = relative_humidity * saturation_vapour_pressure_kpa(temperature_c) / pressure_kpa
    f_oxygen = p * (24.0 + 4.04e4 * vapour_percent * (0.02 + vapour_percent) / (0.391 + vapour_percent))
    f_nitrogen = (
        p * (t / T_REF) ** -0.5 * (9.0 + 280.0 * vapour_percent * np.exp(-4.170 * ((t / T_REF) ** (-1 / 3) - 1.0)))
    )
    wavelength = SPEED_AT_T_REF * np.sqrt(t / T_REF) / f
    neper = 1.84e-11 / p * np.sqrt(t / T_REF) * f**2  # classical absorption
    for (fraction, theta), f_relax in ((OXYGEN, f_oxygen), (NITROGEN, f_nitrogen)):
        per_wavelength_max = 2.0 * np.pi / 35.0 * fraction * (theta / t) ** 2 * np.exp(-theta / t)
        ratio = f / f_relax
        neper = neper + 2.0 * per_wavelength_max * ratio / (1.0 + ratio**2) / wavelength
    return NEPER_TO_DB * neper
