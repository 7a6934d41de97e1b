"""Procedural equirectangular panoramas: findview's built-in data set (no download needed).

Each panorama is ray-cast: every panorama pixel's direction (the pixel -> longitude / latitude mapping
of docs/TASK.md, World and camera: ``lon`` right of the image centre, ``lat`` up) is intersected with a
small 3D scene around a camera at the origin, and the hit surface's texture is sampled at the hit point
(metres -> texels, bilinear, 3-level mip-mapping against aliasing). Views rendered from the panorama are
therefore perspective-consistent.

Scene kinds (the labels of the default data set):

- ``room``: a box room (walls, floor, ceiling) with 3-6 pieces of furniture (boxes);
- ``hall``: a larger room with 6-12 pieces of furniture (shelves, tables, crates);
- ``landscape``: an infinite ground plane, scattered rocks and walls, 3 layers of mountains on the
  horizon, a sky gradient with a sun and a cloud layer (a textured plane 1.5 km up);
- ``village``: the landscape with buildings (windows, doors, signs) and crates.

Textures are painted per surface in metric units with OpenCV: multi-octave value noise (random lattice
values, cubic-interpolated) mixed with per-scene random palettes, sharp-edged blotches, and many random
objects (posters, bookshelves, pixel-art "photos", random text, planks, tiles, stones, windows), so that
no two directions look alike and ORB finds hundreds of keypoints in most perspective views. Everything
derives from ``numpy.random.default_rng(seed)``: the same seed gives the same image on the same
library versions.

Modules:

=========================================  ===========================================================
:mod:`~findview.dataset.synthetic.textures`  value noise, random colours, drawing primitives
:mod:`~findview.dataset.synthetic.painters`  per-surface texture painters (walls, floors, ground, ...)
:mod:`~findview.dataset.synthetic.caster`    the ray caster (planes, boxes) and textured shading
:mod:`~findview.dataset.synthetic.scenes`    the four scene layouts and :func:`generate_panorama`
:mod:`~findview.dataset.synthetic.cache`     the on-disk data set (:func:`ensure_synthetic_images`)
=========================================  ===========================================================

:func:`ensure_synthetic_images` writes the data set under ``<root>/<label>/synth_XXXX.jpg`` (JPEG
quality 95) with a manifest ``<root>/synthetic.json``, regenerating only when the parameters change.
"""

from findview.dataset.synthetic.cache import GENERATOR_VERSION, MANIFEST, ensure_synthetic_images, synthetic_image_seed
from findview.dataset.synthetic.scenes import SCENE_KINDS, generate_panorama

__all__ = [
    "GENERATOR_VERSION",
    "SCENE_KINDS",
    "MANIFEST",
    "generate_panorama",
    "synthetic_image_seed",
    "ensure_synthetic_images",
]
