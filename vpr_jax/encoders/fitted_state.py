"""A fitted state on disk: any pytree of arrays (dicts, lists, tuples, NamedTuples, None)
saved with orbax and restored in the structure it was saved in.

Orbax restores a tree without a target as plain dicts and lists, so the tree's skeleton is
kept beside its arrays (``skeleton.json``): containers by kind, a NamedTuple or a registered
dataclass by its importable class (a dataclass's static fields, ``metadata={"static":
True}``, as JSON), each leaf by its index among the flat ``leaf_NNN`` arrays orbax holds.
Restoring rebuilds the skeleton, gives orbax the target of every leaf's shape and dtype,
and puts the arrays back in their places. Python numbers become 0-d arrays.

Writes are whole or absent: the new folder is written aside and moved into place.

The size of every file orbax wrote is kept too (``sizes.json``): a folder whose arrays were
cut short or lost since (a copy interrupted, a full disk) is refused before orbax reads it.
Orbax reads the leaves concurrently and, when one read fails, closes its event loop while
the others are still in flight; those then report to the closed loop from TensorStore's
threads (``RuntimeError: Event loop is closed``, an unraisable exception) after the error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from vpr_jax.encoders.checkpoints import as_os_error, orbax_noise_held
from vpr_jax.errors import UserError, first_line
from vpr_jax.files import replace_folder

SKELETON, ARRAYS, SIZES = "skeleton.json", "arrays", "sizes.json"


def _skeleton(tree: Any, leaves: list[np.ndarray]) -> Any:
    """JSON data of ``tree``'s structure; its arrays appended to ``leaves``."""
    if tree is None:
        return {"none": None}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # a NamedTuple
        kind = type(tree)
        return {
            "namedtuple": f"{kind.__module__}:{kind.__qualname__}",
            "fields": {f: _skeleton(getattr(tree, f), leaves) for f in tree._fields},
        }
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        kind, fields = type(tree), dataclasses.fields(tree)
        return {
            "dataclass": f"{kind.__module__}:{kind.__qualname__}",
            "fields": {
                f.name: _skeleton(getattr(tree, f.name), leaves)
                for f in fields
                if not f.metadata.get("static")
            },
            "static": {
                f.name: _static(getattr(tree, f.name)) for f in fields if f.metadata.get("static")
            },
        }
    if isinstance(tree, dict):
        if all(isinstance(k, str) for k in tree):
            return {"dict": {k: _skeleton(v, leaves) for k, v in tree.items()}}
        if not all(isinstance(k, str | int) for k in tree):
            raise TypeError(f"a fitted state's dict keys must be text or numbers: {list(tree)}")
        # Flax's pure dicts number the layers of a list: keys kept with their type
        return {"items": [[k, _skeleton(v, leaves)] for k, v in tree.items()]}
    if isinstance(tree, list | tuple):
        kind = "list" if isinstance(tree, list) else "tuple"
        return {kind: [_skeleton(v, leaves) for v in tree]}
    try:
        array = np.asarray(jax.device_get(tree))
    except (TypeError, ValueError) as err:
        raise TypeError(f"a fitted state holds {type(tree).__name__}, not an array") from err
    if array.dtype == object:
        raise TypeError(f"a fitted state holds {type(tree).__name__}, not an array")
    leaves.append(array)
    return {"leaf": len(leaves) - 1, "shape": list(array.shape), "dtype": str(array.dtype)}


def _static(value: Any) -> Any:
    """A static field's value as JSON data: numbers, text, tuples, NamedTuples of them."""
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        kind = type(value)
        return {
            "namedtuple": f"{kind.__module__}:{kind.__qualname__}",
            "fields": {f: _static(getattr(value, f)) for f in value._fields},
        }
    if isinstance(value, list | tuple):
        return {"tuple": [_static(v) for v in value]}
    return value


def _from_static(data: Any) -> Any:
    if isinstance(data, dict) and "tuple" in data:
        return tuple(_from_static(v) for v in data["tuple"])
    if isinstance(data, dict) and "namedtuple" in data:
        return _import(data["namedtuple"])(
            **{f: _from_static(v) for f, v in data["fields"].items()}
        )
    return data


def _import(path: str) -> Any:
    module, name = path.split(":")
    found = importlib.import_module(module)
    for part in name.split("."):
        found = getattr(found, part)
    return found


def _rebuild(skeleton: Any, leaves: dict[str, Any]) -> Any:
    (kind, value), *_ = skeleton.items()
    if kind == "none":
        return None
    if kind == "leaf":
        return leaves[f"leaf_{value:03d}"]
    if kind == "dict":
        return {k: _rebuild(v, leaves) for k, v in value.items()}
    if kind == "items":
        return {k: _rebuild(v, leaves) for k, v in value}
    if kind in ("list", "tuple"):
        items = [_rebuild(v, leaves) for v in value]
        return items if kind == "list" else tuple(items)
    fields = {f: _rebuild(v, leaves) for f, v in skeleton["fields"].items()}
    static = {f: _from_static(v) for f, v in skeleton.get("static", {}).items()}
    return _import(value)(**fields, **static)


def _targets(skeleton: Any, out: dict) -> dict:
    """Every leaf's shape and dtype, as orbax's restore target."""
    if "leaf" in skeleton:
        out[f"leaf_{skeleton['leaf']:03d}"] = jax.ShapeDtypeStruct(
            tuple(skeleton["shape"]), np.dtype(skeleton["dtype"])
        )
        return out
    if "fields" in skeleton:  # a NamedTuple
        children = list(skeleton["fields"].values())
    elif "dict" in skeleton:
        children = list(skeleton["dict"].values())
    elif "items" in skeleton:
        children = [child for _, child in skeleton["items"]]
    else:  # list, tuple or none
        children = next(iter(skeleton.values())) or []
    for child in children:
        _targets(child, out)
    return out


@contextlib.contextmanager
def _checkpointer() -> Iterator[ocp.Checkpointer]:
    """Synchronous, and this process's alone: with several processes (``mesh.distributed``)
    process 0 writes, and orbax must not wait for the others at a barrier. Closed on the way
    out, whether the save or restore succeeded or not."""
    me = ocp.options.MultiprocessingOptions(
        primary_host=jax.process_index(), active_processes={jax.process_index()}
    )
    handler = ocp.StandardCheckpointHandler(multiprocessing_options=me)
    checkpointer = ocp.Checkpointer(handler, multiprocessing_options=me)
    try:
        yield checkpointer
    finally:
        checkpointer.close()


def _sizes(arrays: Path) -> dict[str, int]:
    """Every file under ``arrays``, by its path there, with its size in bytes."""
    return {
        path.relative_to(arrays).as_posix(): path.stat().st_size
        for path in sorted(arrays.rglob("*"))
        if path.is_file()
    }


def _damage(folder: Path) -> str | None:
    """What is missing or cut short among the files orbax wrote, as ``sizes.json`` recorded
    them (None: all there; a folder saved without the record is left to orbax)."""
    try:
        recorded = json.loads((folder / SIZES).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as err:
        return f"{SIZES}: {err}"
    found = _sizes(folder / ARRAYS)
    for name, size in recorded.items():
        if name not in found:
            return f"{ARRAYS}/{name} is missing"
        if found[name] != size:
            return f"{ARRAYS}/{name} has {found[name]} bytes, saved with {size}"
    return None


def save_state(folder: Path, state: Any, files: dict[str, str] | None = None) -> None:
    """Write ``state`` (and the text ``files``, name -> content) as the folder ``folder``,
    whole: aside first, then moved into place over any older one."""
    folder = Path(folder).expanduser().resolve()
    leaves: list[np.ndarray] = []
    skeleton = _skeleton(state, leaves)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        arrays = {f"leaf_{i:03d}": leaf for i, leaf in enumerate(leaves)}
        try:
            with orbax_noise_held(), _checkpointer() as checkpointer:
                checkpointer.save(staging / ARRAYS, args=ocp.args.StandardSave(arrays))
        except (ValueError, RuntimeError) as err:  # a write fault, as the OSError it was
            raise as_os_error(err, folder) from None
        (staging / SIZES).write_text(json.dumps(_sizes(staging / ARRAYS)))
        (staging / SKELETON).write_text(json.dumps(skeleton))
        for name, text in (files or {}).items():
            (staging / name).write_text(text)
        replace_folder(staging, folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def restore_state(folder: Path) -> Any:
    """The state ``save_state`` wrote, in its structure (numpy arrays as leaves). A folder
    that holds none, or whose arrays are cut short: UserError naming it."""
    folder = Path(folder).expanduser().resolve()
    try:
        skeleton = json.loads((folder / SKELETON).read_text())
    except (OSError, ValueError) as err:
        raise UserError(
            f"{folder} holds no fitted state ({SKELETON}: {err}): point at a folder a sweep "
            "saved (python -m experiments.encoders LOGDIR lists them)"
        ) from None
    targets = _targets(skeleton, {})
    damage = _damage(folder) if targets else None  # found before orbax reads (see above)
    leaves = {}
    try:
        if targets and damage is None:
            with _checkpointer() as checkpointer:
                leaves = checkpointer.restore(
                    folder / ARRAYS, args=ocp.args.StandardRestore(targets)
                )
    except Exception as err:  # orbax and TensorStore raise many kinds for a damaged folder
        damage = first_line(err)[:200]
    if damage is not None:
        raise UserError(
            f"{folder} has a damaged or incomplete fitted state ({damage}): "
            "rerun the sweep that saved it (delete the folder first)"
        )
    return _rebuild(skeleton, leaves)
