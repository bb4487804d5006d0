"""Facts defined once: status codes, column names, physical constants, defaults.

Every module that needs one of these imports it from here.
"""
from __future__ import annotations

# --------------------------------------------------------------------------
# Recovery status codes (GLACiAR's meaning, Carrasco et al. 2018, Sect. 2.4)
# --------------------------------------------------------------------------
STATUS_ISOLATED = 0            #: detected, no original source under its footprint
STATUS_BLENDED_FAINTER = 1     #: blended with a fainter original source (recovered)
STATUS_BLENDED_PASSED = 2      #: blended with a brighter source, passes overlap+flux tests (recovered)
STATUS_BLENDED_FAILED = -1     #: blended with a brighter source, fails them (not recovered)
STATUS_LOW_SN = -2             #: detected, S/N below the threshold
STATUS_NOT_DETECTED = -3       #: nothing in the search box

STATUS_CODES = (STATUS_ISOLATED, STATUS_BLENDED_FAINTER, STATUS_BLENDED_PASSED,
                STATUS_BLENDED_FAILED, STATUS_LOW_SN, STATUS_NOT_DETECTED)
RECOVERED_STATUSES = (STATUS_ISOLATED, STATUS_BLENDED_FAINTER, STATUS_BLENDED_PASSED)
STATUS_LABELS = {
    STATUS_ISOLATED: "isolated",
    STATUS_BLENDED_FAINTER: "blended_fainter",
    STATUS_BLENDED_PASSED: "blended_brighter_passed",
    STATUS_BLENDED_FAILED: "blended_brighter_failed",
    STATUS_LOW_SN: "low_sn",
    STATUS_NOT_DETECTED: "not_detected",
}

# Per-source quality flags (bit field, column COL_FLAGS)
FLAG_SEP_ERROR = 1             #: sep raised (e.g. deblending overflow) for this source's window
FLAG_WINDOW_AT_LIMIT = 2       #: detection window hit its maximum size before isolating the source
FLAG_STAMP_CLIPPED = 4         #: stamp partly outside the image
FLAG_NO_DATA = 8               #: some band has no data under the input position (survey.coverage)
#: the detection has a pixel at or above SATUR_LEVEL in the detection band (SExtractor's FLAGS
#: value 4, OBJ_SATUR; glaciar's value 4 was already FLAG_STAMP_CLIPPED, so the bit differs)
FLAG_SATURATED = 16
#: behind a lens: |magnification| > LENS_MAX_MAGNIFICATION or the image's axis ratio below the
#: renderer's Q_MIN; injected with the shape clipped (glaciar.engine.lensed, docs/lensing.md)
FLAG_LENS_EXTREME = 64

# --------------------------------------------------------------------------
# Physical constants
# --------------------------------------------------------------------------
C_ANGSTROM_PER_S = 2.99792458e18   #: speed of light [Angstrom / s]
AB_ZEROPOINT_FNU = -48.60          #: m_AB = -2.5 log10(f_nu [erg/s/cm^2/Hz]) - 48.60
LYA_REST_ANGSTROM = 1215.67        #: Lyman-alpha rest wavelength [Angstrom]
LYLIMIT_REST_ANGSTROM = 911.75     #: Lyman limit rest wavelength [Angstrom]
UV_REST_ANGSTROM = 1600.0          #: rest wavelength of M_UV [Angstrom]
FAINT_MAG_LIMIT = 50.0             #: bands fainter than this get no stamp (GLACiAR's rule)

# --------------------------------------------------------------------------
# Per-source columns of the results store
# --------------------------------------------------------------------------
COL_FIELD = "field"
COL_Z = "z"                     #: input redshift
COL_MAG = "mag"                 #: nominal magnitude of the task (bin centre)
COL_MAG_INPUT = "mag_input"     #: total input AB magnitude in the detection band (the covariate)
COL_ITERATION = "iteration"
COL_TASK_SEED = "task_seed"
COL_SOURCE = "source_index"     #: index of the source within its task
COL_X = "x"                     #: input position, 0-based pixel (numpy axis 1)
COL_Y = "y"                     #: input position, 0-based pixel (numpy axis 0)
COL_SERSIC_N = "sersic_n"
COL_AXIS_RATIO = "axis_ratio"
COL_PA = "position_angle_deg"
COL_R_EFF_KPC = "r_eff_kpc"
COL_R_EFF_ARCSEC = "r_eff_arcsec"
COL_R_EFF_PIX = "r_eff_pix"
COL_BETA = "beta"
COL_M_UV = "M_uv"
COL_STATUS = "status"
# Lensed fields only (survey.lens; docs/lensing.md).  The r_eff_*, axis_ratio and
# position_angle_deg columns hold the image's (observed) values there, mag_input and
# mag_in_* the observed magnitudes, M_uv the one the observed magnitude gives unmagnified.
COL_MAGNIFICATION = "magnification"        #: signed mu at the source's z
COL_KAPPA = "kappa"                        #: convergence at the source's z
COL_GAMMA = "gamma"                        #: |shear| at the source's z
COL_MAG_INTRINSIC = "mag_intrinsic"        #: detection-band magnitude without the lens
COL_M_UV_INTRINSIC = "M_uv_intrinsic"
COL_R_EFF_ARCSEC_INTRINSIC = "r_eff_arcsec_intrinsic"
COL_R_EFF_KPC_INTRINSIC = "r_eff_kpc_intrinsic"
COL_AXIS_RATIO_INTRINSIC = "axis_ratio_intrinsic"
COL_PA_INTRINSIC = "position_angle_deg_intrinsic"
#: |mu| above which a lensed source is flagged FLAG_LENS_EXTREME (near a critical curve the
#: lens is not linear across a stamp) and its image's major axis clipped to this x intrinsic
LENS_MAX_MAGNIFICATION = 50.0
COL_RECOVERED = "recovered"
COL_SELECTED = "selected"
#: Selection probability a user selection function returned (``selection: {function: ...}``
#: returning floats; ``selected`` is then drawn from it).  Absent for boolean selections.
COL_P_SELECTED = "p_selected"
#: Attribute by which a user selection function declares its version (on the function, or
#: on its module); it enters the run's identity (glaciar.engine.user_selection).
SELECTION_VERSION_ATTRIBUTE = "glaciar_selection_version"
COL_DETECTION_ID = "detection_id"
#: Bit field of FLAG_* values.  Not "flags": a DataFrame column of that name is shadowed by
#: ``DataFrame.flags`` in attribute access (``rows.flags``).
COL_FLAGS = "source_flags"
COL_OVERLAP_FRACTION = "overlap_fraction"
COL_BLEND_ID = "blend_original_id"
COL_BLEND_MAG = "blend_original_mag"
#: Local depth under the source: 5-sigma limiting AB magnitude of the detection band's noise
#: in a circular aperture of radius DEPTH_APERTURE_RADIUS_FWHM x the detection PSF FWHM
#: (see glaciar.engine.depth).  NaN where unknown.
COL_DEPTH = "depth_local"
DEPTH_NSIGMA = 5.0                   #: the depth is a DEPTH_NSIGMA-sigma aperture limit
DEPTH_APERTURE_RADIUS_FWHM = 1.0     #: aperture radius of the local depth [detection PSF FWHM]
DEPTH_BIN_MAG = 0.05                 #: bin width of the per-field area-by-depth histograms [mag]
#: Width of the measured-magnitude bins of the transfer matrices, and of the global lattice
#: (anchored at 0 mag) of the per-task histograms of the measured magnitude [mag].
TRANSFER_MOBS_STEP = 0.2


def band_column(quantity: str, band: str) -> str:
    """Column name of a per-band quantity, e.g. ``band_column("sn", "f160w") == "sn_f160w"``.

    Per-band quantities: ``mag_in`` (total input magnitude), ``mag_in_stamp``
    (magnitude of the flux inside the stamp), ``flux_in`` (input flux, image
    units), ``flux_iso``, ``fluxerr_iso``, ``flux_auto``, ``fluxerr_auto``,
    ``flux_aper{k}``, ``fluxerr_aper{k}``, ``mag`` (measured, from the S/N
    flux definition; NaN when the flux is not positive), ``magerr``, ``sn``,
    ``maglim`` (magnitude of max(flux, 1 sigma error): the usual 1-sigma limit
    for non-detections, so a colour cut never passes on a NaN or 99 magnitude),
    ``mag_auto``/``magerr_auto`` (the total magnitude: Kron/AUTO flux, see
    ``OBS_MAG_QUANTITY``).
    """
    return f"{quantity}_{band.lower()}"


BAND_QUANTITIES = ("mag_in", "mag_in_stamp", "flux_in", "flux_iso", "fluxerr_iso",
                   "flux_auto", "fluxerr_auto", "mag", "magerr", "sn", "maglim", "mag_auto",
                   "magerr_auto")

#: The observed magnitude of the luminosity function: the detection band's total magnitude,
#: from the Kron (AUTO) flux (k = PHOT_AUTOPARAMS, ~94 % of a galaxy's light for SExtractor's
#: 2.5: closer to the total than the ISO magnitude, whose isophote loses 0.1-0.2 mag at the
#: faint end).  Recorded for injections and catalogue alike; the transfer function
#: p(m_obs | m_in, z) and ``glaciar lf`` use it (``band_column(OBS_MAG_QUANTITY, band)``).
OBS_MAG_QUANTITY = "mag_auto"

# --------------------------------------------------------------------------
# Results store layout (relative to the run directory)
# --------------------------------------------------------------------------
RESULTS_DIRNAME = "results"          #: one Parquet file per finished task
MANIFEST_NAME = "manifest.json"
RUN_CONFIG_NAME = "config.yaml"      #: the resolved config the run was made with
ADAPTIVE_ROUNDS_NAME = "adaptive_rounds.json"   #: the adaptive loop's log of rounds (in RUN_DIR)
SUMMARY_DIRNAME = "summary"
SELECTION_FUNCTION_NAME = "selection_function.fits"
CONTEXT_DIRNAME = ".context"        #: field contexts memory-mapped by workers (glaciar.engine.fieldcache)
LOCK_NAME = ".lock"                  #: advisory lock of the run writing into the directory
SHARDS_DIRNAME = ".shards"          #: per-shard locks and records, the set-up lock (glaciar.shards)
FINGERPRINT_CACHE_NAME = ".input_fingerprints.json"   #: input hashes by (path, size, mtime)
#: Format of a run directory.  2: task files named by a hash of the exact task key, with the
#: key and row count in their metadata; manifest with store settings and input fingerprints.
#: Directories of format 1 (no ``store_format`` in the manifest) can be read but not resumed.
STORE_FORMAT = 2

# ---------------------------------------------------------------------------
# grid.box: continuous injection points (glaciar.box)
# ---------------------------------------------------------------------------
BOX_Z_RESOLUTION = 1e-4     #: box points' redshifts are multiples of this (exact keys)
BOX_MAG_RESOLUTION = 1e-4   #: box points' magnitudes are multiples of this [mag]
