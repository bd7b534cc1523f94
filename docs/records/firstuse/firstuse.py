"""Where a study worker's first epoch goes (a fresh process: 25-30 s against 0.3-0.9 s for later epochs,
docs/records/answers): each Warp module's load (compiled or from the kernel cache, Warp's own log), the system's build
and the presets' training step, warm-up phase then joint phase, the first steps of each timed (CUDA graph capture and
cuDNN's autotuning included). Run twice with the same WARP_CACHE_PATH: a cold cache, then a warm one; `--profile`: cProfile's 40 costliest calls
(cumulative) of the first step."""
import cProfile
import pstats
import sys
import time
from pathlib import Path

start = time.perf_counter()
import torch  # noqa: E402
import warp as wp  # noqa: E402

wp.config.quiet = False  # Warp prints every module's load: "Module X ... load on device 'cuda:0' took N ms"
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "step"))
from step_profile import recipe_step  # noqa: E402

print(f"imports {time.perf_counter() - start:.2f} s", flush=True)
mark = time.perf_counter()
model, step, images, labels = recipe_step(cuda_graph=True)
torch.cuda.synchronize()
print(f"build {time.perf_counter() - mark:.2f} s", flush=True)
for index, joint in enumerate([False] * 4 + [True] * 4):
    mark = time.perf_counter()
    profiler = cProfile.Profile() if index == 0 and "--profile" in sys.argv else None
    if profiler:
        profiler.enable()
    step(model, images, labels, index, joint=joint)
    torch.cuda.synchronize()
    if profiler:
        profiler.disable()
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(40)
    print(f"step {index} ({'joint' if joint else 'warm-up'}) {time.perf_counter() - mark:.3f} s", flush=True)
print(f"total {time.perf_counter() - start:.2f} s", flush=True)
