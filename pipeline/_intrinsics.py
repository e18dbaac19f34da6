"""Helpers for Numba intrinsics written in portable LLVM IR (no CPU-specific intrinsics).

The vector types below compile to whatever the CPU offers (SSE, AVX2,
AVX-512, NEON); the arithmetic in each lane is the scalar expression's, in
the same order, so results are bit-identical to the scalar code they replace.
"""

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

_I32 = ir.IntType(32)


def item_pointer(context, builder, signature, args):
    """Codegen: the pointer to arr[index] of an intrinsic whose first arguments are (arr, index)."""
    aryty = signature.args[0]
    ary = context.make_array(aryty)(context, builder, args[0])
    idx = [context.cast(builder, v, t, types.intp)
           for v, t in zip(cgutils.unpack_tuple(builder, args[1]), signature.args[1])]
    return cgutils.get_item_pointer(context, builder, aryty, ary, idx, wraparound=False)


def splat(builder, vt: ir.VectorType, x):
    """Codegen: the vector of type ``vt`` with ``x`` in every lane."""
    one = builder.insert_element(ir.Constant(vt, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(one, one, ir.Constant(ir.VectorType(_I32, vt.count), [0] * vt.count))


@intrinsic
def any_inside4(typingctx, arr, index, x, y):
    """Whether (x, y) lies inside any of four ellipses stored from arr[index] on.

    arr[index] starts 20 contiguous float64, fields-major: the centres' x (4),
    their y (4), 1/ax² (4), 1/ay² (4) and a bias (4).  An ellipse holds the
    point when ``dx * dx * (1/ax²) + dy * dy * (1/ay²) + bias < 1`` with
    dx = x - centre x, dy = y - centre y, evaluated left to right as written:
    the four in one vector pass, bit for bit the scalar tests.
    """
    sig = types.boolean(arr, index, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        vt = ir.VectorType(ir.DoubleType(), 4)
        base = builder.bitcast(item_pointer(context, builder, signature, args), vt.as_pointer())
        cx, cy, ax, ay, bias = (builder.load(builder.gep(base, [ir.Constant(_I32, f)]), align=8)
                                for f in range(5))
        dx = builder.fsub(splat(builder, vt, args[2]), cx)
        dy = builder.fsub(splat(builder, vt, args[3]), cy)
        q = builder.fadd(builder.fadd(builder.fmul(builder.fmul(dx, dx), ax),
                                      builder.fmul(builder.fmul(dy, dy), ay)), bias)
        inside = builder.bitcast(builder.fcmp_ordered("<", q, ir.Constant(vt, [1.0] * 4)), ir.IntType(4))
        return builder.icmp_unsigned("!=", inside, ir.Constant(ir.IntType(4), 0))

    return sig, codegen


@intrinsic
def prefetch(typingctx, arr, index):
    """Ask the CPU to start loading the cache line of arr[index] (index: a tuple of arr.ndim integers)."""
    sig = types.void(arr, index)

    def codegen(context, builder, signature, args):
        ptr = item_pointer(context, builder, signature, args)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p],
                                              ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]))
        # read, high locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3),
                          ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def cttz(typingctx, x):
    """The number of trailing zero bits of a non-zero uint64."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        fn = builder.module.declare_intrinsic("llvm.cttz", [i64], ir.FunctionType(i64, [i64, ir.IntType(1)]))
        return builder.call(fn, [args[0], ir.Constant(ir.IntType(1), 1)])

    return sig, codegen


def _borrow(context, builder, ty, val):
    """Codegen: ``val`` of type ``ty`` with every array in it (arrays, tuples of them) unowned."""
    if isinstance(ty, types.Array):
        src = context.make_array(ty)(context, builder, val)
        dst = context.make_array(ty)(context, builder)
        for name in ("nitems", "itemsize", "data", "shape", "strides"):
            setattr(dst, name, getattr(src, name))
        dst.meminfo = cgutils.get_null_value(dst.meminfo.type)
        dst.parent = cgutils.get_null_value(dst.parent.type)
        return dst._getvalue()
    if isinstance(ty, types.BaseTuple):
        out = val
        for i, t in enumerate(ty):
            out = builder.insert_value(out, _borrow(context, builder, t, builder.extract_value(val, i)), i)
        return out
    return val


@intrinsic
def borrowed(typingctx, x):
    """``x`` (an array, or a tuple of arrays and scalars, nested) with its arrays unowned.

    An unowned array has no memory-info block, so Numba's reference counting of it is a test of a
    null pointer instead of an atomic add and a call: a kernel passing the same arrays to small
    functions millions of times spends a quarter of its time on those atomics otherwise.  Only
    for arrays some caller owns for as long as the result is used (a kernel's arguments, borrowed
    in the kernel itself); never return or store one.
    """
    sig = x(x)

    def codegen(context, builder, signature, args):
        return _borrow(context, builder, signature.args[0], args[0])

    return sig, codegen


@intrinsic
def carve(typingctx, flat, offset, shape):
    """``flat[offset:offset + prod(shape)]`` (a 1-D C-contiguous array) as a C-contiguous array of
    ``shape`` (a tuple of integers), unowned like :func:`borrowed`'s, with no runtime call
    (``reshape`` calls a C helper each time).  For work arrays carved from a buffer the caller
    owns; nothing checks that the part lies inside ``flat``."""
    if not (isinstance(flat, types.Array) and flat.ndim == 1 and flat.layout == "C"
            and isinstance(offset, types.Integer) and isinstance(shape, types.UniTuple)
            and isinstance(shape.dtype, types.Integer)):
        return None
    retty = types.Array(flat.dtype, shape.count, "C")
    sig = retty(flat, offset, shape)

    def codegen(context, builder, signature, args):
        from numba.np.arrayobj import populate_array

        src = context.make_array(signature.args[0])(context, builder, args[0])
        out = context.make_array(retty)(context, builder)
        dims = [context.cast(builder, v, signature.args[2].dtype, types.intp)
                for v in cgutils.unpack_tuple(builder, args[2])]
        itemsize = context.get_constant(types.intp, context.get_abi_sizeof(context.get_data_type(flat.dtype)))
        strides = []
        acc = itemsize
        for d in reversed(dims):
            strides.insert(0, acc)
            acc = builder.mul(acc, d)
        off = context.cast(builder, args[1], signature.args[1], types.intp)
        populate_array(out, data=builder.gep(src.data, [off]), shape=dims, strides=strides, itemsize=itemsize,
                       meminfo=None)
        return out._getvalue()

    return sig, codegen
