"""Four Woop triangle tests at once, bit-identical to the scalar test.

A leaf's triangles are tested one at a time by
:func:`simt_sim.bvh.geometry.woop_test`; Embree tests four per vector. :func:`woop4`
loads four consecutive triangles of a leaf (three float4 rows each), transposes their rows
into 4-lane vectors and evaluates, lane by lane, exactly the scalar test's expressions:
the same float32 operations in the same order (``a * b + c * d + e * f`` as
``(a * b + c * d) + e * f``, no fused multiply-add), ordered comparisons (a NaN fails
them as in the scalar code). Each lane's ``t`` and decision are therefore the scalar
ones, for the ``tmax`` given; the caller walks the lanes in order and re-checks
``t < tmax`` against the ``tmax`` that earlier hits of the leaf shrank, which is all the
scalar loop does differently (``tests/bvh/test_wide.py`` checks the op streams).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from simt_sim.bvh.geometry import TRI_ROUNDING
from simt_sim.bvh.layout import WOOP_FLOAT4_PER_TRI

_F32 = ir.FloatType()
_I32 = ir.IntType(32)
_F4 = ir.VectorType(_F32, 4)
LANES = 4


def _splat(builder: ir.IRBuilder, x) -> ir.Value:
    v = ir.Constant(_F4, ir.Undefined)
    for lane in range(LANES):
        v = builder.insert_element(v, x, _I32(lane))
    return v


def _const(x: float) -> ir.Constant:
    return ir.Constant(_F4, [ir.Constant(_F32, float(x))] * LANES)


@intrinsic
def woop4(typingctx, woop, j, n, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """``(stage masks, t0..t3)`` of the ``n`` (1..4) triangles at float4 ``j``, ``j + 3``, ...

    Bit ``k`` of the mask is set where triangle ``k`` passes the scalar test with this
    ``tmax``, bit ``4 + k`` where it passes the u stage (reaches v) and bit ``8 + k`` where
    its t is in range (reaches u): the stages :func:`~simt_sim.bvh.geometry.woop_test`
    counts. Lanes ``k >= n`` re-read triangle ``j`` and are masked off (no read past the leaf).
    ``woop`` is C-contiguous float32 (s, 4).
    """
    floats = (ox, oy, oz, dx, dy, dz, tmin, tmax)
    if not (
        isinstance(woop, types.Array)
        and woop.dtype == types.float32
        and woop.ndim == 2
        and woop.layout == "C"
        and isinstance(j, types.Integer)
        and isinstance(n, types.Integer)
        and all(t == types.float32 for t in floats)
    ):
        return None
    ret = types.Tuple((types.int32, types.float32, types.float32, types.float32, types.float32))
    sig = ret(woop, j, n, *floats)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        j_v = context.cast(builder, args[1], signature.args[1], types.intp)
        n_v = context.cast(builder, args[2], signature.args[2], types.intp)
        ox_v, oy_v, oz_v, dx_v, dy_v, dz_v, tmin_v, tmax_v = args[3:]

        def intp(x: int) -> ir.Constant:
            return ir.Constant(j_v.type, x)

        rows = []  # per lane: the float4 of its first row
        for k in range(LANES):
            lane = builder.select(builder.icmp_signed("<", intp(k), n_v), intp(k), intp(0))
            rows.append(builder.add(j_v, builder.mul(lane, intp(WOOP_FLOAT4_PER_TRI))))

        def row_vectors(offset):
            """The 4 components (x, y, z, w) of row ``offset`` of every lane's triangle."""
            loaded = []
            for r in rows:
                idx = builder.mul(
                    builder.add(r, ir.Constant(j_v.type, offset)), ir.Constant(j_v.type, 4)
                )
                ptr = builder.bitcast(builder.gep(ary.data, [idx]), _F4.as_pointer())
                loaded.append(builder.load(ptr, align=4))
            a, b, c, d = loaded
            ab_lo = builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(_I32, 4), [0, 4, 1, 5]))
            ab_hi = builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(_I32, 4), [2, 6, 3, 7]))
            cd_lo = builder.shuffle_vector(c, d, ir.Constant(ir.VectorType(_I32, 4), [0, 4, 1, 5]))
            cd_hi = builder.shuffle_vector(c, d, ir.Constant(ir.VectorType(_I32, 4), [2, 6, 3, 7]))
            m = ir.VectorType(_I32, 4)
            x = builder.shuffle_vector(ab_lo, cd_lo, ir.Constant(m, [0, 1, 4, 5]))
            y = builder.shuffle_vector(ab_lo, cd_lo, ir.Constant(m, [2, 3, 6, 7]))
            z = builder.shuffle_vector(ab_hi, cd_hi, ir.Constant(m, [0, 1, 4, 5]))
            w = builder.shuffle_vector(ab_hi, cd_hi, ir.Constant(m, [2, 3, 6, 7]))
            return x, y, z, w

        fadd, fmul, fsub, fdiv = builder.fadd, builder.fmul, builder.fsub, builder.fdiv

        i4 = ir.VectorType(_I32, 4)
        sign_off = ir.Constant(i4, [ir.Constant(_I32, 0x7FFFFFFF)] * LANES)

        def fabs(v):  # clear the sign bits: exactly |v|, NaN included
            return builder.bitcast(builder.and_(builder.bitcast(v, i4), sign_off), _F4)

        def dot3(ax, ay, az, bx, by, bz):
            return fadd(fadd(fmul(ax, bx), fmul(ay, by)), fmul(az, bz))

        org = [_splat(builder, v) for v in (ox_v, oy_v, oz_v)]
        dirn = [_splat(builder, v) for v in (dx_v, dy_v, dz_v)]
        w0x, w0y, w0z, w0w = row_vectors(0)
        dn = dot3(*dirn, w0x, w0y, w0z)
        t = fdiv(fsub(w0w, dot3(*org, w0x, w0y, w0z)), dn)
        in_range = builder.and_(
            builder.fcmp_ordered(">", t, _splat(builder, tmin_v)),
            builder.fcmp_ordered("<", t, _splat(builder, tmax_v)),
        )
        t2 = fabs(fadd(t, t))
        px, py, pz = (fadd(fabs(o), fmul(t2, fabs(d))) for o, d in zip(org, dirn, strict=True))
        slope = fdiv(
            fadd(fadd(fadd(fabs(w0w), fmul(px, fabs(w0x))), fmul(py, fabs(w0y))),
                 fmul(pz, fabs(w0z))),
            fabs(dn),
        )  # fmt: skip

        def coordinate(offset):
            wx, wy, wz, ww = row_vectors(offset)
            dw = dot3(*dirn, wx, wy, wz)
            c = fadd(fadd(ww, dot3(*org, wx, wy, wz)), fmul(t, dw))
            bound = fadd(fadd(fadd(fabs(ww), fmul(px, fabs(wx))), fmul(py, fabs(wy))),
                         fmul(pz, fabs(wz)))  # fmt: skip
            err = fmul(_const(TRI_ROUNDING), fadd(bound, fadd(fmul(_const(0.5), fabs(c)),
                                                              fmul(slope, fabs(dw)))))  # fmt: skip
            return c, err

        u, eu = coordinate(1)
        v, ev = coordinate(2)
        u_ok = builder.and_(in_range, builder.fcmp_ordered(">=", u, builder.fneg(eu)))
        ok = builder.and_(u_ok, builder.fcmp_ordered(">=", v, builder.fneg(ev)))
        ok = builder.and_(
            ok, builder.fcmp_ordered("<=", fadd(u, v), fadd(_const(1.0), fadd(eu, ev)))
        )
        mask = ir.Constant(_I32, 0)
        for k in range(LANES):
            valid = builder.icmp_signed("<", intp(k), n_v)
            for field, passed in enumerate((ok, u_ok, in_range)):
                bit = builder.and_(builder.extract_element(passed, _I32(k)), valid)
                shift = _I32(k + LANES * field)
                mask = builder.or_(mask, builder.shl(builder.zext(bit, _I32), shift))
        out = [mask] + [builder.extract_element(t, _I32(k)) for k in range(LANES)]
        return context.make_tuple(builder, signature.return_type, out)

    return sig, codegen
