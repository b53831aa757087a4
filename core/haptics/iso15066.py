"""ISO/TS 15066:2016 biomechanical limits per body region (Annex A), for the force constraint.

Values from ISO/TS 15066:2016 "Robots and robotic devices - Collaborative robots", Annex A:
Table A.2 (maximum permissible quasi-static contact force and pressure; transient contact is
allowed at twice the quasi-static values, except for the skull/forehead and the face, for which the
standard gives no transient values: transient contact with the head is not permissible) and
Table A.3 (effective mass ``m_H`` and spring constant ``k`` of each region, for the energy
transfer model of transient contact). The pressure of a region is the **lowest** of the pressures
of its specific body areas (e.g. chest: sternum 120 N/cm^2, pectoral muscle 170 N/cm^2 -> 120).

=============================  ==========  ==========  ===========  ======  ========
region (key)                   F_qs (N)    F_tr (N)    p_qs N/cm^2  k N/mm  m_H (kg)
=============================  ==========  ==========  ===========  ======  ========
skull_forehead                 130         --          110          150     4.4
face                           65          --          110          75      4.4
neck                           150         300         140          50      1.2
back_shoulders                 210         420         160          35      40
chest                          140         280         120          25      40
abdomen                        110         220         140          10      40
pelvis                         180         360         210          25      40
upper_arm_elbow                150         300         190          30      3
lower_arm_wrist                160         320         180          40      2
hand_finger                    140         280         190          75      0.6
thigh_knee                     220         440         220          50      75
lower_leg                      130         260         210          60      75
=============================  ==========  ==========  ===========  ======  ========

These are pain-onset thresholds measured on healthy adults; for patients in rehabilitation the
force constraint applies a further safety factor (:class:`~.force.ForceConstraintConfig`). The
numbers are transcribed from the standard's tables; check them against the current edition
(ISO 10218-2:2025 Annex A carries them on) before relying on them for a risk assessment.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import NamedTuple

from ..errors import ConfigError, InputError
from ..validation import as_finite_scalar

_CM2_PER_M2 = 1.0e4
_N_PER_M_PER_N_PER_MM = 1.0e3

CONTACT_TYPES = ("quasi_static", "transient")


class BodyRegion(NamedTuple):
    """One body region of ISO/TS 15066 Annex A.

    Attributes
    ----------
    key
        Identifier used in scene files (``"chest"``).
    title
        The standard's name of the region.
    quasi_static_force_n
        Maximum permissible quasi-static contact force (N), Table A.2.
    transient_force_n
        Maximum permissible transient contact force (N); ``None`` where the standard gives none
        (transient contact with the head is not permissible).
    quasi_static_pressure_n_per_cm2
        Lowest maximum permissible quasi-static pressure of the region's body areas (N/cm^2).
    spring_constant_n_per_mm
        Effective spring constant ``k`` (N/mm), Table A.3.
    effective_mass_kg
        Effective mass ``m_H`` of the body region (kg), Table A.3.
    """

    key: str
    title: str
    quasi_static_force_n: float
    transient_force_n: float | None
    quasi_static_pressure_n_per_cm2: float
    spring_constant_n_per_mm: float
    effective_mass_kg: float

    @property
    def transient_pressure_n_per_cm2(self) -> float | None:
        """Transient pressure (N/cm^2): twice the quasi-static one; ``None`` where not permitted."""
        if self.transient_force_n is None:
            return None
        return 2.0 * self.quasi_static_pressure_n_per_cm2

    def force_limit_n(self, contact: str = "quasi_static", contact_area_m2: float = 0.0) -> float:
        """Permissible contact force (N) for a contact type, optionally also pressure-limited.

        Parameters
        ----------
        contact
            ``"quasi_static"`` or ``"transient"``. Where the standard has no transient value
            (skull/forehead, face) the quasi-static one is returned: the stricter value.
        contact_area_m2
            Contact area (m^2); if > 0 the limit is also at most ``pressure * area``.
        """
        if contact not in CONTACT_TYPES:
            raise ConfigError(f"contact = {contact!r}: must be one of {', '.join(CONTACT_TYPES)}")
        area = as_finite_scalar(contact_area_m2, "contact_area_m2")
        if area < 0.0:
            raise InputError(f"contact_area_m2 = {area}: must be >= 0")
        force = self.quasi_static_force_n
        pressure = self.quasi_static_pressure_n_per_cm2
        if contact == "transient" and self.transient_force_n is not None:
            force = self.transient_force_n
            pressure = 2.0 * self.quasi_static_pressure_n_per_cm2
        if area > 0.0:
            force = min(force, pressure * area * _CM2_PER_M2)
        return force


def _region(
    key: str, title: str, f_qs: float, transient: bool, p_qs: float, k: float, m_h: float
) -> BodyRegion:
    return BodyRegion(key, title, f_qs, 2.0 * f_qs if transient else None, p_qs, k, m_h)


#: The body regions of ISO/TS 15066:2016 Annex A (see the module docstring for the table).
BODY_REGIONS: Mapping[str, BodyRegion] = MappingProxyType(
    {
        r.key: r
        for r in (
            _region("skull_forehead", "Skull and forehead", 130.0, False, 110.0, 150.0, 4.4),
            _region("face", "Face", 65.0, False, 110.0, 75.0, 4.4),
            _region("neck", "Neck", 150.0, True, 140.0, 50.0, 1.2),
            _region("back_shoulders", "Back and shoulders", 210.0, True, 160.0, 35.0, 40.0),
            _region("chest", "Chest", 140.0, True, 120.0, 25.0, 40.0),
            _region("abdomen", "Abdomen", 110.0, True, 140.0, 10.0, 40.0),
            _region("pelvis", "Pelvis", 180.0, True, 210.0, 25.0, 40.0),
            _region(
                "upper_arm_elbow", "Upper arms and elbow joints", 150.0, True, 190.0, 30.0, 3.0
            ),
            _region(
                "lower_arm_wrist", "Lower arms and wrist joints", 160.0, True, 180.0, 40.0, 2.0
            ),
            _region("hand_finger", "Hands and fingers", 140.0, True, 190.0, 75.0, 0.6),
            _region("thigh_knee", "Thighs and knees", 220.0, True, 220.0, 50.0, 75.0),
            _region("lower_leg", "Lower legs", 130.0, True, 210.0, 60.0, 75.0),
        )
    }
)

#: Everyday names a scene may use for a region.
ALIASES: Mapping[str, str] = MappingProxyType(
    {
        "head": "skull_forehead",
        "skull": "skull_forehead",
        "forehead": "skull_forehead",
        "back": "back_shoulders",
        "shoulder": "back_shoulders",
        "shoulders": "back_shoulders",
        "torso": "chest",
        "belly": "abdomen",
        "upper_arm": "upper_arm_elbow",
        "elbow": "upper_arm_elbow",
        "forearm": "lower_arm_wrist",
        "lower_arm": "lower_arm_wrist",
        "wrist": "lower_arm_wrist",
        "hand": "hand_finger",
        "finger": "hand_finger",
        "fingers": "hand_finger",
        "thigh": "thigh_knee",
        "knee": "thigh_knee",
        "shin": "lower_leg",
        "calf": "lower_leg",
    }
)

#: Region keys, in table order (the choices of a body-region parameter).
REGION_KEYS: tuple[str, ...] = tuple(BODY_REGIONS)


def body_region(name: str) -> BodyRegion:
    """The ISO/TS 15066 region named ``name`` (a key or alias, case, blanks and hyphens ignored).

    Raises
    ------
    ConfigError
        Naming ``name`` and listing the known regions, if it is not one of them.
    """
    if not isinstance(name, str):
        raise ConfigError(f"body region {name!r}: expected a name")
    key = name.strip().lower().replace("-", "_").replace(" ", "_").replace("/", "_")
    key = ALIASES.get(key, key)
    region = BODY_REGIONS.get(key)
    if region is None:
        known = ", ".join(REGION_KEYS)
        raise ConfigError(f"body region {name!r}: not an ISO/TS 15066 region (known: {known})")
    return region


def reduced_mass_kg(human_mass_kg: float, robot_mass_kg: float) -> float:
    """``mu = (1/m_H + 1/m_R)^-1`` (kg); an infinite robot mass gives ``m_H``."""
    m_h = as_finite_scalar(human_mass_kg, "human_mass_kg")
    m_r = float(robot_mass_kg)
    if not m_h > 0.0 or not m_r > 0.0 or math.isnan(m_r):
        raise InputError(f"masses must be > 0 kg, got m_H = {m_h}, m_R = {m_r}")
    return 1.0 / (1.0 / m_h + 1.0 / m_r)


def max_transient_speed_mps(
    region: str | BodyRegion, robot_mass_kg: float, contact_area_m2: float = 0.0
) -> float:
    """Highest relative speed at which a transient contact stays within the region's limit (m/s).

    ISO/TS 15066 Annex A.3.2 energy transfer model: ``v_max = F_max / sqrt(mu k)`` with the
    reduced mass ``mu`` of body region and robot and the region's spring constant ``k``. Use it to
    choose the velocity constraint's ``v_min_mps`` near a body part.

    Parameters
    ----------
    region
        Region key/alias or :class:`BodyRegion`.
    robot_mass_kg
        The robot's effective mass along the contact normal at the HIP (kg), e.g.
        :func:`~.force.effective_mass_kg`; ``inf`` is allowed (rigid direction).
    contact_area_m2
        If > 0, the force is also limited by the transient pressure times this area.
    """
    reg = region if isinstance(region, BodyRegion) else body_region(region)
    force = reg.force_limit_n("transient", contact_area_m2)
    mu = reduced_mass_kg(reg.effective_mass_kg, robot_mass_kg)
    k = reg.spring_constant_n_per_mm * _N_PER_M_PER_N_PER_MM
    return force / math.sqrt(mu * k)
