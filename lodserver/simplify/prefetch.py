"""Software prefetch for the decimation kernel: ask for a row before it is needed.

A greedy collapse order visits the mesh at random: every popped candidate
lands in a neighbourhood that is not in cache, and the kernel's walks over it
are chains of dependent loads (corner -> face -> vertex), so on a mesh too
large for the cache a collapse spends much of its time waiting on memory.
Where the kernel knows an address a while before it reads it (the next
candidate at the heap's root, the neighbours a collapse will re-rank),
``prefetch`` starts the load so that the wait overlaps useful work.

``prefetch(a, i)`` hints the cache line holding ``a[i]`` (``a[i, 0]`` for a
2-D array): it reads nothing, cannot fault, and changes no result; it only
moves time. Compiled to one ``prefetcht0`` on x86 (LLVM's ``llvm.prefetch``,
read, high locality); a target without such an instruction drops it.

numba's intrinsics cannot run as Python, so where numba is told to run the
kernels as Python (``NUMBA_DISABLE_JIT``, the first run of a small input,
``lodserver.first_run``) both hints are plain functions that do nothing.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import config
from numba.core import cgutils
from numba.extending import intrinsic

_I8P = ir.IntType(8).as_pointer()
_I32 = ir.IntType(32)
# llvm.prefetch(address, rw = 0: read, locality = 3: keep in every level, 1: data cache)
_ARGUMENTS = (ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1))


def _hint(context, builder, array_type, array, at):
    """Emit ``llvm.prefetch`` of the element ``at`` (intp values, one per dimension)."""
    data = context.make_array(array_type)(context, builder, array)
    pointer = cgutils.get_item_pointer(context, builder, array_type, data, at,
                                       wraparound=False, boundscheck=False)
    hint = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.VoidType(), [_I8P, _I32, _I32, _I32]),
        "llvm.prefetch.p0")
    builder.call(hint, [builder.bitcast(pointer, _I8P), *_ARGUMENTS])


@intrinsic
def prefetch(typingctx, array, index):
    """Hint the cache line of ``array[index]`` (``array[index, 0]`` for a 2-D
    array); ``index`` must lie inside the array."""
    if not isinstance(array, types.Array) or not isinstance(index, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        array_type, index_type = signature.args
        zero = context.get_constant(types.intp, 0)
        at = [context.cast(builder, args[1], index_type, types.intp)] + [zero] * (array_type.ndim - 1)
        _hint(context, builder, array_type, args[0], at)
        return context.get_dummy_value()

    return types.void(array, index), codegen


@intrinsic
def prefetch2(typingctx, array, row, column):
    """Hint the cache line of ``array[row, column]`` of a 2-D array (a row
    longer than a cache line needs one hint per line)."""
    if (not isinstance(array, types.Array) or array.ndim != 2
            or not isinstance(row, types.Integer) or not isinstance(column, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        at = [context.cast(builder, value, kind, types.intp)
              for value, kind in zip(args[1:], signature.args[1:])]
        _hint(context, builder, signature.args[0], args[0], at)
        return context.get_dummy_value()

    return types.void(array, row, column), codegen


if config.DISABLE_JIT:
    def prefetch(array, index):     # noqa: F811  (the kernels run as Python: no cache to hint)
        """Nothing: a hint has no meaning to the Python interpreter."""

    def prefetch2(array, row, column):      # noqa: F811
        """Nothing: a hint has no meaning to the Python interpreter."""
