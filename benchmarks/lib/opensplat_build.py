"""OpenSplat, the peer C++ trainer, for side-by-side benchmarks: built from its source archive in
../shared/third_party/ into a folder outside the repository, fed a COLMAP project, timed step by step.

Never part of the project (AGPL-3.0): nothing here copies its source; `build` unpacks the archive into the given
folder and compiles it there.

The build links the torch wheel's own libtorch (libtorch_cpu and libc10: OpenSplat's CPU build calls nothing else)
through a small CMake package written beside the build (`torch_cmake_package`): the wheel's TorchConfig.cmake
looks for the CUDA toolkit when the wheel is a CUDA build, as PyPI's Linux wheel is, and a CPU machine has none.
OpenCV is Debian's (`libopencv-dev`); OpenSplat's other dependencies are in its archive.
"""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tarfile
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import pycolmap
import torch

REPO = Path(__file__).resolve().parents[2]
ARCHIVE = REPO.parent / "shared" / "third_party" / "opensplat-1.2.0.tar.gz"
OPENCV_CONFIGS = ("/usr/lib/*/cmake/opencv4/OpenCVConfig.cmake", "/usr/lib/cmake/opencv4/OpenCVConfig.cmake",
                  "/usr/local/lib/cmake/opencv4/OpenCVConfig.cmake")


def missing_build_dependency(archive: Path = ARCHIVE) -> str | None:
    """Why OpenSplat cannot be built here (the archive or a build tool missing), or None when it can."""
    if not archive.is_file():
        return f"{archive} is not here (OpenSplat's source archive, beside the repository in shared/third_party)"
    for tool in ("cmake", "c++"):
        if shutil.which(tool) is None:
            return f"no {tool} on PATH (Debian: apt-get install cmake g++)"
    if shutil.which("ninja") is None and shutil.which("make") is None:
        return "neither ninja nor make on PATH"
    if not any(glob.glob(pattern) for pattern in OPENCV_CONFIGS):
        return "OpenCV's CMake package is not installed (Debian: apt-get install libopencv-dev)"
    return None


def torch_cmake_package(folder: Path) -> Path:
    """Write <folder>/TorchConfig.cmake: the torch wheel's libtorch_cpu and libc10 with its headers and C++ ABI, as
    the imported target TORCH_LIBRARIES names (module docstring). Returns `folder`."""
    root = Path(torch.__file__).parent
    includes = f"{root}/include;{root}/include/torch/csrc/api/include"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "TorchConfig.cmake").write_text(f"""# benchmarks/lib/opensplat_build.py: the torch wheel's CPU libtorch
set(TORCH_INCLUDE_DIRS "{includes}")
add_library(torch_wheel_cpu INTERFACE IMPORTED)
set_target_properties(torch_wheel_cpu PROPERTIES
  INTERFACE_INCLUDE_DIRECTORIES "{includes}"
  INTERFACE_LINK_LIBRARIES "{root}/lib/libtorch_cpu.so;{root}/lib/libc10.so"
  INTERFACE_COMPILE_DEFINITIONS "_GLIBCXX_USE_CXX11_ABI={int(torch._C._GLIBCXX_USE_CXX11_ABI)}")
set(TORCH_LIBRARIES torch_wheel_cpu)
set(Torch_FOUND TRUE)
""")
    return folder


def build(folder: Path, archive: Path = ARCHIVE, jobs: int = 2) -> Path:
    """The opensplat executable built for the CPU (Release) in `folder`, reused when a build is already there.
    RuntimeError with the build's last output lines when CMake or the compiler fails."""
    binary = folder / "build" / "opensplat"
    if binary.is_file():
        return binary
    with tarfile.open(archive) as tar:
        top = tar.getnames()[0].split("/")[0]
        tar.extractall(folder, filter="data")
    generator = ["-G", "Ninja"] if shutil.which("ninja") else []
    package = torch_cmake_package(folder / "torch_cmake")
    steps = (["cmake", "-S", str(folder / top), "-B", str(folder / "build"), "-DGPU_RUNTIME=CPU",
              "-DCMAKE_BUILD_TYPE=Release", f"-DTorch_DIR={package}", *generator],
             ["cmake", "--build", str(folder / "build"), "--parallel", str(jobs)])
    for command in steps:
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            tail = "\n".join((done.stdout + done.stderr).splitlines()[-30:])
            raise RuntimeError(f"building OpenSplat failed at: {' '.join(command)}\n{tail}")
    return binary


def colmap_project(sparse_dir: Path, images_dir: Path, train_names: set[str], folder: Path) -> Path:
    """A COLMAP project in `folder` (images/, sparse/0/) holding the training frames `train_names` of the model in
    `sparse_dir` and all of its 3D points: the held-out frames are left out, so that OpenSplat trains on the views
    splat_train trains on. Images are linked, not copied. Returns `folder`."""
    model = pycolmap.Reconstruction(str(sparse_dir))
    unknown = train_names - {image.name for image in model.images.values()}
    if unknown:
        raise ValueError(f"{sparse_dir}: no registered frame named {sorted(unknown)[:3]}")
    for image in list(model.images.values()):
        if image.name not in train_names:
            model.deregister_frame(image.frame_id)
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "images").mkdir()
    model.write_binary(str(folder / "sparse" / "0"))
    # every SfM point, as splat_train starts from (deregistering drops the points only held-out frames saw)
    shutil.copyfile(sparse_dir / "points3D.bin", folder / "sparse" / "0" / "points3D.bin")
    for name in sorted(train_names):
        (folder / "images" / name).symlink_to((images_dir / name).resolve())
    return folder


@dataclass
class OpenSplatRun:
    """One timed OpenSplat training."""

    seconds_per_step: float  # from the first step's end to the last's, over the steps between (loading and saving
    # the scene excluded)
    steps: int
    wall_s: float  # the whole process
    num_gaussians: int  # in the written scene
    ply: Path


def ply_vertex_count(ply: Path) -> int:
    """The vertex count a PLY's header declares."""
    with open(ply, "rb") as f:
        for line in f:
            if line.startswith(b"element vertex"):
                return int(line.split()[2])
            if line.strip() == b"end_header":
                break
    raise ValueError(f"{ply}: no 'element vertex' line in the header")


def train(binary: Path, project: Path, iterations: int, downscale: float, cpus: set[int], out_ply: Path,
          extra_args: tuple[str, ...] = ()) -> OpenSplatRun:
    """Train `project` with OpenSplat on the CPU cores `cpus` (its raster workers and libtorch's threads confined
    to them; OMP_NUM_THREADS = their count) for `iterations` steps at images scaled down by `downscale`, writing
    `out_ply` (in the COLMAP frame: OpenSplat keeps the model's coordinates unless told --center). Each printed
    step's line is stamped as it arrives. RuntimeError with the last output lines when it fails."""
    env = {**os.environ, "OMP_NUM_THREADS": str(len(cpus)), "MKL_NUM_THREADS": str(len(cpus))}
    command = [str(binary), str(project), "--cpu", "-n", str(iterations), "-d", f"{downscale:.6f}", "-o",
               str(out_ply), *extra_args]
    started = time.perf_counter()
    stamps: dict[int, float] = {}
    tail: deque[str] = deque(maxlen=30)  # the last output lines, for an error
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                          preexec_fn=lambda: os.sched_setaffinity(0, cpus)) as process:
        for line in process.stdout:
            if line.startswith("Step "):  # "Step 12: 0.0923 [1%]", printed after every CPU step
                stamps[int(line.split()[1].rstrip(":"))] = time.perf_counter()
            tail.append(line.rstrip())
    wall = time.perf_counter() - started
    if process.returncode != 0 or len(stamps) < 2:
        raise RuntimeError(f"{' '.join(command)} failed (exit {process.returncode}):\n" + "\n".join(tail))
    first, last = min(stamps), max(stamps)
    return OpenSplatRun(round((stamps[last] - stamps[first]) / (last - first), 5), last, round(wall, 1),
                        ply_vertex_count(out_ply), out_ply)
