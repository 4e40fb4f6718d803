"""The built-in demo scenes, generated on first use into the cache (:mod:`cusgs_jax.cache`).

* :mod:`.room` — the demo room (photos from scikit-image on a room with a table and boxes, ray cast
  from orbit cameras with exact poses, written as a COLMAP model): ``cusgs-train``'s scene when
  ``data.path`` is not set;
* :mod:`.lens` — the same room seen through a distorting COLMAP lens (``data.demo.lens``), and
  :func:`configured_demo`, the demo a configuration asks for;
* :mod:`.objects` — the room's furniture alone, as an object-centric capture (COLMAP and Blender layouts);
* :mod:`.render` — their geometry, textures, ray casting and cameras; :mod:`.sfm` — their SfM-like points.
"""

from cusgs_jax.cache import default_cache_dir
from cusgs_jax.data.demo.lens import configured_demo
from cusgs_jax.data.demo.room import FORMAT_VERSION, cached_scene, demo_scene_path, generate_demo_scene

__all__ = ["FORMAT_VERSION", "cached_scene", "configured_demo", "default_cache_dir", "demo_scene_path",
           "generate_demo_scene"]
