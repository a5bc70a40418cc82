"""20-sim generated C++ and ANSI-C code, compiled once and called through ctypes.

A 20-sim export is a folder of sources without a Makefile. :class:`TwentySimModel`
recognises the template (C++ class derived from ``Submodel20sim``, or the ANSI-C
``XXInitializeSubmodel`` functions with an optional prefix), reads the signal names
from the ``.info`` file, writes a small ``extern "C"`` shim, and compiles model + shim
into one shared library per model::

    g++ -O2 -fPIC -shared -include cstddef   (C++; some templates need <cstddef> for NULL)
    gcc -O2 -fPIC -shared                    (ANSI-C)

The library is cached under ``$RTLOOP_CACHE_DIR/models`` (default
``~/.cache/rtloop/models``), named by a hash of the sources, the shim, the compiler and
its flags, so a second run starts at once. It is loaded in the task process, in
``initialize`` (prerun); the constructor only parses and builds, so the model pickles.

The shim's C API (``rtloop_*``) takes an instance handle: C++ models may have several
instances in one process. ANSI-C models keep their state in globals; a second live
instance in the same process gets a private copy of the library.

A model's state can be saved and restored (a ``--keep`` run's window is replayed from it,
``runtime/snapshot.py``), through its state arrays, found in the sources (:class:`StateLayout`):

- C++: every ``XXDouble`` array the model's constructor allocates (``m_P = new XXDouble[n]``:
  parameters, variables, states, rates, ...) and every number member of the model class and
  of ``Submodel20sim`` (time, step size, the run state flags). The shim's ``rtloop_state``
  copies them out or in. If that copy does not compile for an export, the library is built
  without it and the state says why it cannot be saved.
- ANSI-C: every number the sources define at file scope (``xx_time``, ``xx_P[]``, ``xx_s[]``,
  ...): the whole model is in them. Their sizes come from the library's symbol table (``nm``).

A member or global rtloop cannot copy (a structure other than 20-sim's matrices, which point into
the arrays; a ``static`` number at file scope; an integration method that keeps a history)
makes the state refused, naming it: never saved half.

In three parts: :mod:`.export` reads an export, :mod:`.build` writes its shim and compiles it,
:mod:`.model` loads and runs it.
"""

from rtloop.models.twentysim.build import build_library as build_library
from rtloop.models.twentysim.build import default_cache_dir as default_cache_dir
from rtloop.models.twentysim.export import TwentySimInfo as TwentySimInfo
from rtloop.models.twentysim.export import inspect as inspect
from rtloop.models.twentysim.model import TwentySimModel as TwentySimModel

__all__ = ["TwentySimInfo", "TwentySimModel", "build_library", "default_cache_dir", "inspect"]
