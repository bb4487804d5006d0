"""The embedded demo survey: a synthetic 4-band BoRG-like field, written as FITS plus a config.

``glaciar demo`` needs no downloads.  :func:`make_demo_images` builds, in
memory and in a few seconds, one HST WFC3 pure-parallel-like pointing in the
four BoRG[z8] bands (F160W detection, F098M, F125W, F606W; Carrasco et al.
2018, Sect. 4) drizzled to 0.08"/px, and :func:`build_demo_survey` writes it
to disk with a configuration following ``docs/config-schema.yaml``.

Large mosaics: above ``strips.STRIP_MIN_PIXELS`` (2048^2) :func:`build_demo_survey`
streams the same field into its FITS files by strips of rows
(:func:`glaciar.demo.strips.iter_demo_strips`): peak memory ~1.4 GB at any size
(16000^2 x 4 bands: ~200 s of CPU) instead of ~200 bytes per pixel.  Catalogue
and weight maps are the whole-image ones bit for bit; science pixels differ only
by the FFT rounding of the PSF convolution (a float32 last bit here and there),
which is why the whole-image path is kept below the threshold: the default demo
and the tests' fields stay byte-identical.

What is in the field
--------------------
* **Noise.** Drizzle-like correlated noise: white Gaussian noise convolved
  with the separable overlap kernel of a square drop (side pixfrac x native
  pixel) with the output pixel, normalised so that the *per-pixel* variance
  is exactly ``1 / weight``.  As in real drizzled data the noise in an
  aperture is then larger than ``rms_pixel * sqrt(N_pix)`` (by 1.39x in an
  r = 0.2" aperture for the IR bands at pixfrac 0.8, 0.128" -> 0.08"); F606W (UVIS, 0.04" -> 0.08")
  drops are smaller than an output pixel, so its noise is white.
* **Weights.** Inverse variance maps built from a relative-exposure map: a
  smooth exposure gradient, three dithered exposures of a tilted detector
  footprint (so 1/3 and 2/3 depth along the edges and zero weight -- and
  science = 0 -- in the corners and border where there are no data), two
  slightly shallower IR "blob" patches and, in F606W, a half-depth chip-gap
  stripe.
* **Depths.** ``DEMO_BANDS_SPEC[band].depth_5sigma``: total AB magnitude of
  a point source whose flux inside an r = 0.2" circular aperture is 5 times
  the (correlated) aperture noise, at relative exposure 1 (BoRG quotes this
  quantity; typical 26.7 in F160W, Carrasco et al. 2018 Sect. 4).
  F160W 26.7, F125W 26.8, F098M 26.5, F606W 27.0.
* **Sources.** Background galaxies with dN/dm ~ 10^(0.3 m) in 19 < H < 25,
  flattening to 10^(0.15 m) for 25 < H < 29 (deep near-IR counts); 250 per
  arcmin^2 by default (not confusion-limited; ~65 per arcmin^2 at H < 26, about
  half of a real deep field), Sersic n 0.5-4 tied to three SED types (blue
  star-forming, dusty/intermediate, passive red) that set the colours, sizes from a magnitude-size relation with 0.2 dex scatter,
  random axis ratio and position angle; plus a few stars (two bright).  Each
  band is convolved with its own Moffat (beta = 2.5) PSF.  Source Poisson
  noise uses the band's exposure time (the config's ``gain``).
* **PSF files** are written at a different pixel scale from the images
  (IR at 0.13"/px like Tiny Tim, F606W at 0.04"/px) with a ``PIXSCALE``
  header, so the pipeline exercises PSF resampling.

Conventions: pixel ``(iy, ix)`` covers ``[ix - 1/2, ix + 1/2] x [iy - 1/2,
iy + 1/2]`` (0-based, as :mod:`glaciar.galaxy.psf`); image units are
electrons / s; position angles are counter-clockwise from the +x pixel axis;
``r_eff`` is the half-light semi-major axis.
"""
from .bands import DEMO_BANDS, DEMO_BANDS_SPEC, DEMO_CONFIG_NAME, DEMO_FIELD, DemoBand
from .images import make_demo_images
from .noise import drizzle_noise_kernel
from .survey import build_demo_survey

__all__ = ["DEMO_FIELD", "DEMO_BANDS", "DEMO_BANDS_SPEC", "DEMO_CONFIG_NAME", "DemoBand",
           "drizzle_noise_kernel", "make_demo_images", "build_demo_survey"]
