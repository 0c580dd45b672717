"""A fitted state on disk: any pytree of arrays (dicts, lists, tuples, NamedTuples, None)
saved with orbax and restored in the structure it was saved in.

Orbax restores a tree without a target as plain dicts and lists, so the tree's skeleton is
kept beside its arrays (``skeleton.json``): containers by kind, a NamedTuple or a registered
dataclass by its class's name (``module:qualname``; a dataclass's static fields,
``metadata={"static": True}``, as JSON), each leaf by its index among the flat ``leaf_NNN``
arrays orbax holds, with its shape and dtype. Restoring looks every class the skeleton names
up in a table the caller gives (``types``: the suite's own state types and those of the
methods the user named), never imports one: a name not in it is refused before anything is
read or called. The arrays the skeleton claims are checked against memory before orbax
reads them; then orbax gets the target of every leaf's shape and dtype, and the arrays are
put back in their places. Python numbers become 0-d arrays.

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
import json
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from vpr_jax.encoders.checkpoints import as_os_error, orbax_noise_held
from vpr_jax.errors import UserError, first_line
from vpr_jax.files import replace_folder
from vpr_jax.untrusted import check_claim, claimed_bytes

SKELETON, ARRAYS, SIZES = "skeleton.json", "arrays", "sizes.json"
CONTAINERS = ("none", "leaf", "dict", "items", "list", "tuple")
CLASSES = ("namedtuple", "dataclass")


def type_name(kind: type) -> str:
    """How a skeleton names a class, and how a table of state types finds it."""
    return f"{kind.__module__}:{kind.__qualname__}"


class NotAState(ValueError):
    """A skeleton that asks for what its table does not hold, or is not one ``_skeleton``
    writes."""


def _skeleton(tree: Any, leaves: list[np.ndarray]) -> Any:
    """JSON data of ``tree``'s structure; its arrays appended to ``leaves``."""
    if tree is None:
        return {"none": None}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # a NamedTuple
        return {
            "namedtuple": type_name(type(tree)),
            "fields": {f: _skeleton(getattr(tree, f), leaves) for f in tree._fields},
        }
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        fields = dataclasses.fields(tree)
        return {
            "dataclass": type_name(type(tree)),
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
        return {
            "namedtuple": type_name(type(value)),
            "fields": {f: _static(getattr(value, f)) for f in value._fields},
        }
    if isinstance(value, list | tuple):
        return {"tuple": [_static(v) for v in value]}
    return value


def _from_static(data: Any, types: Mapping[str, type]) -> Any:
    if isinstance(data, dict) and "tuple" in data:
        return tuple(_from_static(v, types) for v in data["tuple"])
    if isinstance(data, dict) and "namedtuple" in data:
        fields = {f: _from_static(v, types) for f, v in data["fields"].items()}
        return _known(data["namedtuple"], types)(**fields)
    return data


def _known(name: Any, types: Mapping[str, type]) -> type:
    if not isinstance(name, str) or name not in types:
        raise NotAState(f"it names the type {name!r}, which is no fitted state this suite knows")
    return types[name]


def _rebuild(skeleton: Any, leaves: dict[str, Any], types: Mapping[str, type]) -> Any:
    (kind, value), *_ = skeleton.items()
    if kind == "none":
        return None
    if kind == "leaf":
        return leaves[f"leaf_{value:03d}"]
    if kind == "dict":
        return {k: _rebuild(v, leaves, types) for k, v in value.items()}
    if kind == "items":
        return {k: _rebuild(v, leaves, types) for k, v in value}
    if kind in ("list", "tuple"):
        items = [_rebuild(v, leaves, types) for v in value]
        return items if kind == "list" else tuple(items)
    fields = {f: _rebuild(v, leaves, types) for f, v in skeleton["fields"].items()}
    static = {f: _from_static(v, types) for f, v in skeleton.get("static", {}).items()}
    return _known(value, types)(**fields, **static)


def _check(skeleton: Any, types: Mapping[str, type], out: dict) -> dict:
    """Every leaf's shape and dtype (orbax's restore target), after checking that the
    skeleton is one ``_skeleton`` writes and names only classes of ``types`` (NotAState)."""
    if not isinstance(skeleton, dict) or not skeleton:
        raise NotAState(f"it holds {type(skeleton).__name__} where a node belongs")
    kind = next(iter(skeleton))
    if kind not in (*CONTAINERS, *CLASSES):
        raise NotAState(f"it holds a node of kind {kind!r}")
    if kind in CLASSES:
        _known(skeleton[kind], types)
        _check_static(skeleton.get("static", {}), types)
        children = skeleton["fields"].values()
    elif kind == "leaf":
        if not isinstance(skeleton["leaf"], int):
            raise NotAState(f"it numbers a leaf {skeleton['leaf']!r}")
        claimed_bytes(skeleton["shape"], skeleton["dtype"])  # counts and numbers only
        out[f"leaf_{skeleton['leaf']:03d}"] = jax.ShapeDtypeStruct(
            tuple(skeleton["shape"]), np.dtype(skeleton["dtype"])
        )
        return out
    elif kind == "dict":
        children = skeleton["dict"].values()
    elif kind == "items":
        children = [child for _, child in skeleton["items"]]
    else:  # list, tuple or none
        children = skeleton[kind] or []
    for child in children:
        _check(child, types, out)
    return out


def _check_static(data: Any, types: Mapping[str, type]) -> None:
    """A dataclass's static values: JSON data, tuples of it and NamedTuples of ``types``."""
    if isinstance(data, dict):
        if "namedtuple" in data:
            _known(data["namedtuple"], types)
        for value in data.values():
            _check_static(value, types)
    elif isinstance(data, list):
        for value in data:
            _check_static(value, types)


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


def restore_state(folder: Path, types: Mapping[str, type]) -> Any:
    """The state ``save_state`` wrote, in its structure (numpy arrays as leaves), its classes
    found in ``types`` (``type_name`` -> class). A folder that holds none, whose skeleton
    names a class not in ``types``, whose arrays claim more than memory or are cut short:
    UserError naming it, before anything is read or called."""
    folder = Path(folder).expanduser().resolve()
    try:
        skeleton = json.loads((folder / SKELETON).read_text())
    except (OSError, ValueError, RecursionError) as err:
        raise UserError(
            f"{folder} holds no fitted state ({SKELETON}: {first_line(err)}): point at a "
            "folder a sweep saved (python -m experiments.encoders LOGDIR lists them)"
        ) from None
    try:
        targets = _check(skeleton, types, {})
    except NotAState as err:
        raise UserError(
            f"{folder / SKELETON} is refused, nothing read or run: {err}; load only folders "
            "a sweep saved, naming the method of your own that saved one "
            "(load_encoder(folder, plugins=['module:name']))"
        ) from None
    except (KeyError, TypeError, ValueError, AttributeError, RecursionError) as err:
        raise UserError(
            f"{folder / SKELETON} is not a fitted state's skeleton ({first_line(err)}): "
            "rerun the sweep that saved it (delete the folder first)"
        ) from None
    claimed = sum(int(np.prod(t.shape)) * t.dtype.itemsize for t in targets.values())
    check_claim(claimed, str(folder / SKELETON), "load only folders a sweep saved")
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
    try:
        return _rebuild(skeleton, leaves, types)
    except (KeyError, TypeError, ValueError, AttributeError) as err:  # other fields, say
        raise UserError(
            f"{folder / SKELETON} does not fit the state types of this suite "
            f"({first_line(err)}): rerun the sweep that saved it"
        ) from None
