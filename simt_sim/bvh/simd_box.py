"""A node's two child-box tests in 4-wide vectors, bit-identical to the scalar ones.

The traversal spends most of its time testing a node's two child boxes: twelve slab
distances ``(plane - o) * idir``, then ``max``/``min`` reductions. Written as scalars that
is about fifty instructions per node, which LLVM does not vectorise on its own (the
planes are picked per ray by direction sign). :func:`node_child_intervals_simd` emits the
same arithmetic as :func:`simt_sim.bvh.geometry.node_child_intervals` on three 4-lane vectors
(about half the instructions), so the tracer and recorder run faster with every decision
unchanged.

Why every result is bit for bit the scalar one, for any input (NaN, infinities, signed
zeros included):

- each lane computes ``(plane - o) * idir`` with the same float32 operations and the
  same operands (lanes are swapped per ray so the near plane sits where the scalar code
  picks it by sign); no fused multiply-add, no reassociation;
- far planes are multiplied by ``-idir`` instead of ``idir``: IEEE rounding is symmetric
  in sign, so the lane holds exactly ``-slab``; ``min`` of values is then ``-max`` of
  their negations, and numba's scalar ``min(a, b) = b if b < a else a`` maps onto
  ``max(-a, -b) = -b if -b > -a else -a`` with the same operand order, so even a NaN
  propagates from the same side; ``BOX_ROUNDING * (-x) = -(BOX_ROUNDING * x)`` exactly;
- the reductions keep the scalar expression's nesting and operand order.

``tests/bvh/test_simd_box.py`` checks it against the scalar function on random and extreme
inputs; the traversal tests check the op streams against the scalar function too.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from simt_sim.bvh.geometry import BOX_ROUNDING
from simt_sim.bvh.layout import NODE_FLOATS

_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_F4 = ir.VectorType(_F32, 4)
_B4 = ir.VectorType(ir.IntType(1), 4)
_SWAP_PAIRS = (1, 0, 3, 2)


def _shuffle(builder: ir.IRBuilder, a, b, lanes: tuple[int, ...]):
    return builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(_I32, len(lanes)), lanes))


def _splat(builder: ir.IRBuilder, values: list, vtype: ir.VectorType):
    v = ir.Constant(vtype, ir.Undefined)
    for lane, x in enumerate(values):
        v = builder.insert_element(v, x, _I32(lane))
    return v


def _max(builder: ir.IRBuilder, a, b):
    """Numba's scalar ``max(a, b)`` lane by lane: ``b if b > a else a``."""
    return builder.select(builder.fcmp_ordered(">", b, a), b, a)


@intrinsic
def node_child_intervals_simd(typingctx, nodes, k, ox, oy, oz, idx, idy, idz, tmin, tmax):
    """``(tnear0, tfar0, tnear1, tfar1)`` of node ``k``: :func:`node_child_intervals`'s
    result, bit for bit, for C-contiguous float32 ``nodes`` of 16 columns."""
    if not (
        isinstance(nodes, types.Array)
        and nodes.dtype == types.float32
        and nodes.ndim == 2
        and nodes.layout == "C"
        and isinstance(k, types.Integer)
        and all(t == types.float32 for t in (ox, oy, oz, idx, idy, idz, tmin, tmax))
    ):
        return None
    sig = types.UniTuple(types.float32, 4)(nodes, k, ox, oy, oz, idx, idy, idz, tmin, tmax)

    def codegen(context, builder, signature, args):
        nodes_v, k_v, ox_v, oy_v, oz_v, ix, iy, iz, tmin_v, tmax_v = args
        ary = context.make_array(signature.args[0])(context, builder, nodes_v)
        row = context.cast(builder, k_v, signature.args[1], types.intp)
        row = builder.mul(row, ir.Constant(row.type, NODE_FLOATS))
        vec_ptr = builder.bitcast(builder.gep(ary.data, [row]), _F4.as_pointer())
        # cols 0-3: child 0 x/y planes, 4-7: child 1 x/y, 8-11: z planes of both.
        xy0, xy1, z01 = (builder.load(builder.gep(vec_ptr, [_I32(j)]), align=4) for j in range(3))
        zero = ir.Constant(_F32, 0.0)
        neg_x = builder.fcmp_ordered("<", ix, zero)
        neg_y = builder.fcmp_ordered("<", iy, zero)
        neg_z = builder.fcmp_ordered("<", iz, zero)
        # A negative inverse enters through hi: swap (lo, hi) so lanes read (near, far).
        swap_xy = _splat(builder, [neg_x, neg_x, neg_y, neg_y], _B4)
        swap_z = _splat(builder, [neg_z] * 4, _B4)
        xy0 = builder.select(swap_xy, _shuffle(builder, xy0, xy0, _SWAP_PAIRS), xy0)
        xy1 = builder.select(swap_xy, _shuffle(builder, xy1, xy1, _SWAP_PAIRS), xy1)
        z01 = builder.select(swap_z, _shuffle(builder, z01, z01, _SWAP_PAIRS), z01)
        o_xy = _splat(builder, [ox_v, ox_v, oy_v, oy_v], _F4)
        o_z = _splat(builder, [oz_v] * 4, _F4)
        nix, niy, niz = builder.fneg(ix), builder.fneg(iy), builder.fneg(iz)
        inv_xy = _splat(builder, [ix, nix, iy, niy], _F4)
        inv_z = _splat(builder, [iz, niz, iz, niz], _F4)
        s0 = builder.fmul(builder.fsub(xy0, o_xy), inv_xy)  # near x0, -far x0, near y0, -far y0
        s1 = builder.fmul(builder.fsub(xy1, o_xy), inv_xy)  # the same for child 1
        sz = builder.fmul(builder.fsub(z01, o_z), inv_z)  # near z0, -far z0, near z1, -far z1
        sx = _shuffle(builder, s0, s1, (0, 1, 4, 5))  # near x0, -far x0, near x1, -far x1
        sy = _shuffle(builder, s0, s1, (2, 3, 6, 7))
        mxy = _max(builder, sx, sy)
        tmin4 = _splat(builder, [tmin_v] * 4, _F4)
        neg_tmax4 = _splat(builder, [builder.fneg(tmax_v)] * 4, _F4)
        rounding4 = _splat(builder, [ir.Constant(_F32, float(BOX_ROUNDING))] * 4, _F4)
        # tnear = max(max(x, y), max(z, tmin)); -tfar = max(R * max(max(-x, -y), -z), -tmax)
        near = _max(builder, mxy, _max(builder, sz, tmin4))
        neg_far = _max(builder, builder.fmul(rounding4, _max(builder, mxy, sz)), neg_tmax4)
        out = [
            builder.extract_element(near, _I32(0)),
            builder.fneg(builder.extract_element(neg_far, _I32(1))),
            builder.extract_element(near, _I32(2)),
            builder.fneg(builder.extract_element(neg_far, _I32(3))),
        ]
        return context.make_tuple(builder, signature.return_type, out)

    return sig, codegen
