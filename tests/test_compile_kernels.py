"""One warm-up for every compiled kernel: after ``ms.compile_kernels()`` no Numba kernel of the
package is left to compile on first use.

A kernel counts as warmed when it has a compiled signature, or when it is called only from
other kernels and one that calls it is warmed: its machine code is part of theirs (a caller
loaded from Numba's disk cache brings its callees' code with it and leaves their own
dispatchers empty; a kernel inlined with ``inline="always"`` never has code of its own). A
kernel named anywhere in the package's Python code (outside kernels) must have a signature of
its own. The check runs in a fresh interpreter, so that the kernels the other tests ran do not
count.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import subprocess
import sys
import types

import pytest
from numba.core.dispatcher import Dispatcher

import multislit as ms


def _code_names(code: types.CodeType) -> set[str]:
    """The global and attribute names a code object and the code nested in it refer to."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _code_names(const)
    return names


def _python_functions(module: types.ModuleType):
    """The plain Python functions and methods defined in ``module``."""
    for obj in vars(module).values():
        if isinstance(obj, Dispatcher):
            continue
        if inspect.isfunction(obj) and obj.__module__ == module.__name__:
            yield obj
        elif inspect.isclass(obj) and obj.__module__ == module.__name__:
            for member in vars(obj).values():
                func = getattr(member, "__func__", member)
                func = getattr(func, "fget", func)  # properties
                if inspect.isfunction(func):
                    yield func


def unwarmed(modules: list[types.ModuleType]) -> list[str]:
    """The Numba kernels defined in ``modules`` that have no machine code yet (see the module).

    Parameters
    ----------
    modules : the modules whose kernels are checked (those defined in each)

    Returns
    -------
    list of str, ``module.kernel`` of every kernel left to compile, sorted
    """
    kernels: dict[int, tuple[str, Dispatcher]] = {}
    for module in modules:
        for name, obj in vars(module).items():
            if isinstance(obj, Dispatcher) and obj.py_func.__module__ == module.__name__:
                kernels[id(obj)] = (f"{module.__name__}.{name}", obj)

    def referenced(func) -> set[int]:
        glb = func.__globals__
        return {
            id(glb[n])
            for n in _code_names(func.__code__)
            if isinstance(glb.get(n), Dispatcher) and id(glb[n]) in kernels
        }

    callees = {k: referenced(d.py_func) for k, (_, d) in kernels.items()}
    from_python: set[int] = set()
    for module in modules:
        for func in _python_functions(module):
            from_python |= referenced(func)
    warm = {k for k, (_, d) in kernels.items() if d.signatures}
    todo = list(warm)
    while todo:  # a warmed kernel's callees are compiled into it
        for callee in callees[todo.pop()]:
            if callee not in warm and callee not in from_python:
                warm.add(callee)
                todo.append(callee)
    return sorted(name for k, (name, _) in kernels.items() if k not in warm)


def _package_modules() -> list[types.ModuleType]:
    return [
        importlib.import_module(info.name)
        for info in pkgutil.walk_packages(ms.__path__, ms.__name__ + ".")
    ]


_FAKE = """
from numba import njit

@njit(inline="always")
def _helper(x):
    return x + 1.0

@njit
def _entry(x):
    return _helper(x) * 2.0

@njit
def _called_from_python(x):
    return x - 1.0

def wrapper(x):
    return _called_from_python(x)
"""


def test_unwarmed_flags_a_kernel_left_to_compile() -> None:
    mod = types.ModuleType("fake_kernels")
    exec(compile(_FAKE, "fake_kernels", "exec"), mod.__dict__)
    assert unwarmed([mod]) == [
        "fake_kernels._called_from_python",
        "fake_kernels._entry",
        "fake_kernels._helper",
    ]
    mod._entry(1.0)
    assert not mod._helper.signatures  # inlined: no code of its own
    # the entry point compiled, its helper with it; the kernel Python calls is left
    assert unwarmed([mod]) == ["fake_kernels._called_from_python"]
    mod._called_from_python(1.0)
    assert unwarmed([mod]) == []


def test_package_has_kernels_to_check() -> None:
    names = {
        f"{m.__name__}.{n}"
        for m in _package_modules()
        for n, obj in vars(m).items()
        if isinstance(obj, Dispatcher) and obj.py_func.__module__ == m.__name__
    }
    # a kernel of each stage package, as the walk must find them
    for kernel in (
        "multislit.stripes.centres",
        "multislit.identify.evidence",
        "multislit.reconstruct.triangulation",
        "multislit.calibrate.row_order",
    ):
        assert any(n.startswith(kernel + ".") for n in names), kernel


_CHECK = """
import importlib, pkgutil, sys
sys.path.insert(0, {tests!r})
import multislit as ms
ms.compile_kernels()
from test_compile_kernels import _package_modules, unwarmed
left = unwarmed(_package_modules())
print("\\n".join(left))
sys.exit(1 if left else 0)
"""


@pytest.mark.slow  # a fresh interpreter compiles every kernel
def test_compile_kernels_warms_every_kernel() -> None:
    tests = os.path.dirname(os.path.abspath(__file__))
    run = subprocess.run(
        [sys.executable, "-c", _CHECK.format(tests=tests)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, (
        "kernels left to compile after ms.compile_kernels() (give them a warm-up in their "
        f"stage's compile_kernels):\n{run.stdout}{run.stderr[-2000:]}"
    )
