"""Four child boxes of a wide node tested at once, bit-identical to the scalar test.

The wide layouts store each plane of a node's children as one row (structure of arrays,
:mod:`simt_sim.bvh.wide`), so four children's ``lo.x`` are four adjacent floats: the SIMD
node layout the lecture's shallow BVH is meant for. :func:`four_child_test` loads each
plane row as a 4-lane vector and evaluates, lane by lane, exactly the scalar expressions
of :func:`simt_sim.bvh.wide_traverse.wide_traverse_ray`'s child loop::

    tnear = max(max(sx, sy), max(sz, tmin))
    tfar  = min(BOX_ROUNDING * min(min(fx, fy), fz), tmax)

with numba's ``max(a, b) = b if b > a else a`` and ``min(a, b) = b if b < a else a``
(operand order kept, so a NaN propagates from the same side) and no fused multiply-add:
each lane's result is the scalar one bit for bit (``tests/bvh/test_wide.py`` checks it on
random and extreme inputs). Unlike the binary node's vector test, no lane shuffle is
needed: a ray's near and far plane rows are picked once per ray by direction sign.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from simt_sim.bvh.geometry import BOX_ROUNDING

_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_F4 = ir.VectorType(_F32, 4)


def _splat(builder: ir.IRBuilder, x) -> ir.Value:
    v = ir.Constant(_F4, ir.Undefined)
    for lane in range(4):
        v = builder.insert_element(v, x, _I32(lane))
    return v


def _max(builder: ir.IRBuilder, a, b):
    """numba's ``max(a, b)`` lane by lane: ``b if b > a else a``."""
    return builder.select(builder.fcmp_ordered(">", b, a), b, a)


def _min(builder: ir.IRBuilder, a, b):
    """numba's ``min(a, b)`` lane by lane: ``b if b < a else a``."""
    return builder.select(builder.fcmp_ordered("<", b, a), b, a)


@intrinsic
def four_child_test(
    typingctx, nodes, node, base, nx, ny, nz, fx, fy, fz, ox, oy, oz, idx, idy, idz, tmin, tmax
):
    """``(hit mask, tnear0..3)`` of children ``base .. base+3`` of row ``node``.

    ``nx, ny, nz`` (``fx, fy, fz``) are the column offsets of the near (far) x, y, z plane
    rows; bit ``c`` of the mask is set where child ``base + c``'s ``tnear <= tfar``.
    ``nodes`` is C-contiguous float32, 2-D.
    """
    ints = (node, base, nx, ny, nz, fx, fy, fz)
    floats = (ox, oy, oz, idx, idy, idz, tmin, tmax)
    if not (
        isinstance(nodes, types.Array)
        and nodes.dtype == types.float32
        and nodes.ndim == 2
        and nodes.layout == "C"
        and all(isinstance(t, types.Integer) for t in ints)
        and all(t == types.float32 for t in floats)
    ):
        return None
    ret = types.Tuple((types.int32, types.float32, types.float32, types.float32, types.float32))
    sig = ret(nodes, *ints, *floats)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        as_intp = [
            context.cast(builder, v, t, types.intp)
            for v, t in zip(args[1:9], signature.args[1:9], strict=True)
        ]
        node_v, base_v, nx_v, ny_v, nz_v, fx_v, fy_v, fz_v = as_intp
        ox_v, oy_v, oz_v, ix, iy, iz, tmin_v, tmax_v = args[9:]
        ncols = builder.extract_value(ary.shape, 1)
        row = builder.add(builder.mul(node_v, ncols), base_v)

        def plane(col, o, inv):
            ptr = builder.bitcast(builder.gep(ary.data, [builder.add(row, col)]), _F4.as_pointer())
            return builder.fmul(builder.fsub(builder.load(ptr, align=4), _splat(builder, o)),
                                _splat(builder, inv))  # fmt: skip

        sx, sy, sz = plane(nx_v, ox_v, ix), plane(ny_v, oy_v, iy), plane(nz_v, oz_v, iz)
        gx, gy, gz = plane(fx_v, ox_v, ix), plane(fy_v, oy_v, iy), plane(fz_v, oz_v, iz)
        near = _max(builder, _max(builder, sx, sy), _max(builder, sz, _splat(builder, tmin_v)))
        rounding = _splat(builder, ir.Constant(_F32, float(BOX_ROUNDING)))
        far = _min(
            builder,
            builder.fmul(rounding, _min(builder, _min(builder, gx, gy), gz)),
            _splat(builder, tmax_v),
        )
        hit = builder.fcmp_ordered("<=", near, far)
        mask = ir.Constant(_I32, 0)
        for lane in range(4):
            bit = builder.zext(builder.extract_element(hit, _I32(lane)), _I32)
            mask = builder.or_(mask, builder.shl(bit, _I32(lane)))
        out = [mask] + [builder.extract_element(near, _I32(lane)) for lane in range(4)]
        return context.make_tuple(builder, signature.return_type, out)

    return sig, codegen
