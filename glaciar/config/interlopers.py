"""The ``interlopers:`` section: a low-redshift population injected to measure contamination.

Absent (the default) the run is exactly what it was without it.  Present, the run also
injects interlopers -- dusty star-forming and Balmer-break galaxies at z in ``z_range``
(:mod:`glaciar.galaxy.interloper_seds`) -- into the same images, through the same
detection, classification and selection, in tasks of their own
(:mod:`glaciar.engine.interlopers`); ``glaciar fit`` then writes the fraction that
passes the selection per measured magnitude (docs/contamination.md).
"""
from __future__ import annotations

from pydantic import Field, model_validator

from ..galaxy.population import SourceModel
from .common import At, Float, Int
from .section import MAX_ABS_MAGNITUDE, MAX_R_EFF_KPC, Section, engine_default, float_list

__all__ = ["DustyFamilyConfig", "BalmerFamilyConfig", "NumberCountsConfig", "InterloperConfig",
           "COUNTS_DEFAULT"]

#: Default number counts log10 dN/dm [arcmin^-2 mag^-1] = a + b (m - m0): faint
#: near-infrared galaxy counts (HST WFC3/IR H band, Windhorst et al. 2011, ApJS 193, 27,
#: their Fig. 11: ~1e5 galaxies per 0.5 mag per deg^2 at H_AB ~ 26, faint-end slope
#: ~0.2 dex / mag); read off the figure, good to ~0.2 dex -- give your own band's counts.
COUNTS_DEFAULT = {"a": 1.75, "b": 0.2, "m0": 26.0}


def _range(lo, hi, **bounds):
    return Field((lo, hi), **bounds)


def _ordered(model, *names):
    for name in names:
        lo, hi = getattr(model, name)
        if hi < lo:
            raise At(f"must be [low, high] with low <= high, got [{lo:g}, {hi:g}]", name)


class DustyFamilyConfig(Section):
    """Dusty star-forming interlopers: a power law behind the Calzetti et al. (2000) law."""

    weight: Float = Field(0.10, ge=0, le=1, description="fraction of the galaxies of counts: "
                          "that this family stands for (illustrative default)")
    beta: float_list(min_length=2, max_length=2, ge=-5.0, le=5.0) = Field(
        (-2.2, -1.6), description="intrinsic UV slope beta, uniform in [low, high] "
                                  "(f_lambda ∝ lambda^beta)")
    a_v: float_list(min_length=2, max_length=2, ge=0.0, le=20.0) = Field(
        (1.0, 4.0), description="V-band attenuation A_V [mag], uniform in [low, high] "
                                "(Calzetti law, R_V = 4.05)")

    @model_validator(mode="after")
    def _check(self):
        _ordered(self, "beta", "a_v")
        return self


class BalmerFamilyConfig(Section):
    """Quiescent / Balmer-break interlopers: a two-slope continuum with a 4000 A break."""

    weight: Float = Field(0.05, ge=0, le=1, description="fraction of the galaxies of counts: "
                          "that this family stands for (illustrative default)")
    d4000: float_list(min_length=2, max_length=2, ge=1.0, le=5.0) = Field(
        (1.4, 2.2), description="break strength D4000 (Bruzual 1983), uniform in [low, high]")
    beta_blue: Float = Field(2.0, ge=-5.0, le=10.0, description="f_lambda slope blueward of "
                                                                "the break")
    beta_red: Float = Field(-1.0, ge=-5.0, le=5.0, description="f_lambda slope redward of "
                                                               "the break")
    a_v: float_list(min_length=2, max_length=2, ge=0.0, le=20.0) = Field(
        (0.0, 0.5), description="V-band attenuation A_V [mag], uniform in [low, high]")

    @model_validator(mode="after")
    def _check(self):
        _ordered(self, "d4000", "a_v")
        return self


class NumberCountsConfig(Section):
    """Surface density of interlopers per detection-band magnitude."""

    a: Float = Field(COUNTS_DEFAULT["a"], ge=-10, le=10,
                     description="log10 dN/dm at m0 [arcmin^-2 mag^-1]")
    b: Float = Field(COUNTS_DEFAULT["b"], ge=-2, le=2, description="slope d log10 N / dm "
                                                                   "[dex / mag]")
    m0: Float = Field(COUNTS_DEFAULT["m0"], ge=-MAX_ABS_MAGNITUDE, le=MAX_ABS_MAGNITUDE,
                      description="pivot magnitude [AB]; default counts: Windhorst et al. "
                                  "(2011) near-infrared, docs/contamination.md")


def _src(name):
    return engine_default(SourceModel, name)


class InterloperConfig(Section):
    """A low-z interloper population (docs/contamination.md); absent: none is injected."""

    z_range: float_list(min_length=2, max_length=2, gt=0.0, le=15.0) = Field(
        (1.0, 6.0), description="redshifts of the interlopers: nodes every z_step from low to "
                                "high, equally weighted")
    z_step: Float = Field(0.5, gt=0, le=10, description="step of the redshift nodes")
    mag_range: float_list(min_length=2, max_length=2, ge=-MAX_ABS_MAGNITUDE,
                          le=MAX_ABS_MAGNITUDE) = Field(
        (24.0, 29.0), description="detection-band AB magnitudes [low, high]: cells of mag_step, "
                                  "each source uniform in its cell")
    mag_step: Float = Field(0.5, gt=0, le=5, description="width of the magnitude cells [mag]")
    n_per_task: Int = Field(50, ge=1, description="interlopers per task (field, z node, "
                                                  "magnitude cell, iteration)")
    n_iterations: Int = Field(1, ge=1, description="iterations per (field, z node, magnitude "
                                                   "cell)")
    dusty: DustyFamilyConfig = Field(default_factory=DustyFamilyConfig,
                                     description="dusty star-forming family")
    balmer: BalmerFamilyConfig = Field(default_factory=BalmerFamilyConfig,
                                       description="Balmer-break (quiescent) family")
    counts: NumberCountsConfig = Field(default_factory=NumberCountsConfig,
                                       description="number counts the passing fraction is "
                                                   "weighted to (per arcmin^2 per mag)")
    r_eff_kpc_z6: Float = Field(0.8, gt=0, le=MAX_R_EFF_KPC,
                                description="half-light radius law as in source: r_e at z = 6 "
                                            "[proper kpc] ... (default: late-type galaxies of "
                                            "~1e9 Msun, van der Wel et al. 2014)")
    size_evolution: Float = Field(-0.75, description="... times ((1+z)/7)^size_evolution")
    r_eff_scatter_dex: Float = Field(0.0, ge=0, le=2, description="log-normal scatter of r_e "
                                                                  "[dex] ...")
    size_bins: Int = Field(3, ge=1, le=100, description="... drawn from this many equal-"
                           "probability nodes with its variance (sources share templates)")
    sersic_indices: float_list(ge=0.2, le=10.0) = Field((1.0, 4.0), description="Sersic "
                                                        "indices n ...")
    sersic_fractions: float_list(ge=0.0, le=1.0) = Field((0.7, 0.3), description="... and "
                                                         "their fractions (sum to 1)")

    @model_validator(mode="after")
    def _check(self):
        _ordered(self, "z_range", "mag_range")
        total = self.dusty.weight + self.balmer.weight
        if not 0 < total <= 1:
            raise At(f"dusty.weight + balmer.weight must be in (0, 1] (fractions of the "
                     f"galaxies in counts:), got {total:g}", "dusty", "weight")
        if len(self.sersic_fractions) != len(self.sersic_indices):
            raise At(f"has {len(self.sersic_fractions)} value(s) but sersic_indices has "
                     f"{len(self.sersic_indices)}", "sersic_fractions")
        if abs(sum(self.sersic_fractions) - 1.0) > 1e-6:
            raise At(f"must sum to 1, got {sum(self.sersic_fractions):g}", "sersic_fractions")
        return self

    def z_nodes(self) -> list[float]:
        """The redshift nodes: low, low + z_step, ... up to high (rounded to 1e-9)."""
        return _nodes(self.z_range, self.z_step)

    def mag_cells(self) -> list[float]:
        """Centres of the magnitude cells of width mag_step covering mag_range."""
        lo, hi = self.mag_range
        n = max(1, int(round((hi - lo) / self.mag_step)))
        return [round(lo + (i + 0.5) * self.mag_step, 9) for i in range(n)]


def _nodes(rng, step) -> list[float]:
    lo, hi = rng
    n = int(round((hi - lo) / step + 1e-9))
    return [round(lo + i * step, 9) for i in range(n + 1) if lo + i * step <= hi + 1e-9]
