import sys, time, json, os
sys.path.insert(0, "/work/main/benchmarks")
import jax, jax.numpy as jnp, numpy as np
from scenes import random_scene
from cusgs_jax.splat import rasterize
KEYS = ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")
s = random_scene(50000, 256, 256)
args = [jnp.asarray(s[k]) for k in KEYS]
w = jnp.asarray(np.random.default_rng(1).normal(size=(256, 256, 3)), jnp.float32)
f = jax.jit(jax.grad(lambda *a: jnp.sum(rasterize(*a, 256, 256, tile_size=8, max_pairs=400000).image * w), argnums=(0, 1, 2, 3, 4)))
jax.block_until_ready(f(*args))
t = []
for _ in range(9):
    t0 = time.perf_counter(); jax.block_until_ready(f(*args)); t.append(time.perf_counter() - t0)
print(json.dumps(dict(src=os.environ.get("PYTHONPATH"), median_s=float(np.median(t)), min_s=float(min(t)))))
