// Shared device code of the kernels on the compressed 8-wide BVH (cwbvh_*.cu).
//
// Byte contract (see simt_sim/bvh/cwbvh.py, layout "cwbvh"; Ylitie, Karras & Laine 2017):
//   nodes : float4[5 * n_nodes]; node i is 80 bytes, nodes[5i .. 5i+4], little-endian:
//           bytes  0-11  p.x p.y p.z     float32 grid origin
//           bytes 12-14  e.x e.y e.z     uint8 biased exponent: the grid step is 2^(e - 127)
//           byte  15     imask           bit s set iff slot s is an interior child
//           bytes 16-19  child base      node index of the first interior child
//           bytes 20-23  triangle base   triangle (3 float4 of woop) of the first leaf
//           bytes 24-31  meta[8]         0 empty; 0b001_11sss interior (24 + s);
//                                        leaf: unary count (0b001, 0b011, 0b111) in bits
//                                        5-7, offset 0..23 from the triangle base in 0-4
//           bytes 32-79  q_lo.x[8] q_lo.y[8] q_lo.z[8] q_hi.x[8] q_hi.y[8] q_hi.z[8]
//           Interior children are stored contiguously in slot order: slot s is node
//           child base + popc(imask & ((1 << s) - 1)). Node 0 is the root.
//   woop, tri_index : 3 float4 per triangle in leaf order, no end markers (a leaf's count
//           is in its meta); tri_index[j] is the scene triangle at float4 j.
//   rays  : common.cuh's.
//
// Traversal state (simt_sim/bvh/cwbvh_traverse.py): a node group (child base, imask, hit
// bits in visiting order: a ray of octant o visits slot s at bit s ^ o) and a triangle
// group (triangle base, one bit per triangle still to test). A stack entry is a node group.
//
// Box test: each plane is decoded as p + 2^e * q (one rounding: the product is exact, so
// one FFMA is the same value), then the binary kernels' slab arithmetic on the near and far
// plane of each axis (picked by the sign of the inverse direction), tfar carrying the
// watertight rounding bound, as cwbvh_traverse.py. With SIMT_PUBLISHED_TESTS the paper's
// form: per node the scaled inverse direction and origin offset, one FFMA per plane.
#pragma once

#include "common.cuh"

#define SIMT_CWBVH_WIDTH 8              // children per node
#define SIMT_CWBVH_NODE_FLOAT4 5        // float4 per node: 80 bytes
#define SIMT_CWBVH_OFF_E 12             // byte offsets in a node (simt_sim/bvh/cwbvh.py)
#define SIMT_CWBVH_OFF_IMASK 15
#define SIMT_CWBVH_OFF_CHILD_BASE 16
#define SIMT_CWBVH_OFF_TRI_BASE 20
#define SIMT_CWBVH_OFF_META 24
#define SIMT_CWBVH_OFF_QLO 32           // + 8 * axis
#define SIMT_CWBVH_OFF_QHI 56           // + 8 * axis
#define SIMT_CWBVH_INTERIOR_LOW 24      // meta & 31 of an interior slot is 24 + slot
// Per-ray stack of node groups: at most one pushed per level below the root, so a tree of
// WideStats.depth < 64 needs fewer than SIMT_STACK_SIZE entries.
#define SIMT_CWBVH_STACK_SIZE SIMT_STACK_SIZE

// A node group: child base, and (imask << 8) | hit bits in visiting order.
struct CwGroup {
    unsigned base;
    unsigned bits;
};

// Outcome of one node step: the interior children hit (visiting-order bits) and the
// triangles of the leaf children hit (bits at their offset from the triangle base).
struct CwHit {
    unsigned base;
    unsigned imask;
    unsigned node_hits;
    unsigned tri_base;
    unsigned tri_hits;
};

__device__ __forceinline__ unsigned simt_cw_byte(unsigned word, int i)
{
    return (word >> (8 * i)) & 0xffu;
}

__device__ __forceinline__ unsigned simt_f4_word(float4 v, int i)
{
    return __float_as_uint(i == 0 ? v.x : (i == 1 ? v.y : (i == 2 ? v.z : v.w)));
}

// Byte b (0..79) of the node whose five float4 are n[0..4].
__device__ __forceinline__ unsigned simt_cw_node_byte(const float4 (&n)[SIMT_CWBVH_NODE_FLOAT4],
                                                      int b)
{
    return simt_cw_byte(simt_f4_word(n[b / 16], (b / 4) % 4), b % 4);
}

// Fetch node `node` (5 float4) and test its 8 child boxes against [r.tmin, tmax].
__device__ __forceinline__ CwHit simt_cw_intersect_node(const float4* __restrict__ nodes,
                                                         unsigned node, const Ray& r,
                                                         unsigned octant, float tmax)
{
    float4 n[SIMT_CWBVH_NODE_FLOAT4];
#pragma unroll
    for (int i = 0; i < SIMT_CWBVH_NODE_FLOAT4; ++i)
        n[i] = __ldg(nodes + SIMT_CWBVH_NODE_FLOAT4 * node + i);
    const float px = n[0].x;
    const float py = n[0].y;
    const float pz = n[0].z;
    const unsigned w3 = __float_as_uint(n[0].w);  // e.x e.y e.z imask
    // 2^(e - 127) as float bits: the biased exponent in bits 23-30
    const float sx = __uint_as_float(simt_cw_byte(w3, 0) << 23);
    const float sy = __uint_as_float(simt_cw_byte(w3, 1) << 23);
    const float sz = __uint_as_float(simt_cw_byte(w3, 2) << 23);
    const bool neg_x = r.idir.x < 0.0f;
    const bool neg_y = r.idir.y < 0.0f;
    const bool neg_z = r.idir.z < 0.0f;
#ifdef SIMT_PUBLISHED_TESTS
    const float ax = sx * r.idir.x, bx = (px - r.orig.x) * r.idir.x;
    const float ay = sy * r.idir.y, by = (py - r.orig.y) * r.idir.y;
    const float az = sz * r.idir.z, bz = (pz - r.orig.z) * r.idir.z;
    const float rounding = 1.0f;
#else
    const float rounding = SIMT_BOX_ROUNDING;
#endif
    CwHit h;
    h.imask = simt_cw_byte(w3, 3);
    h.base = __float_as_uint(n[1].x);
    h.tri_base = __float_as_uint(n[1].y);
    h.node_hits = 0;
    h.tri_hits = 0;
    // The near and far planes of each axis, 4 slots per word, picked once per node by the
    // sign of the inverse direction (12 word selects instead of 48 plane selects).
    unsigned qn[3][2], qf[3][2];
#pragma unroll
    for (int a = 0; a < 3; ++a) {
        const bool neg = a == 0 ? neg_x : (a == 1 ? neg_y : neg_z);
#pragma unroll
        for (int half = 0; half < 2; ++half) {
            const int lo = (SIMT_CWBVH_OFF_QLO + 8 * a) / 4 + half;  // word index in the node
            const int hi = (SIMT_CWBVH_OFF_QHI + 8 * a) / 4 + half;
            const unsigned wlo = simt_f4_word(n[lo / 4], lo % 4);
            const unsigned whi = simt_f4_word(n[hi / 4], hi % 4);
            qn[a][half] = neg ? whi : wlo;
            qf[a][half] = neg ? wlo : whi;
        }
    }
#pragma unroll
    for (int s = 0; s < SIMT_CWBVH_WIDTH; ++s) {
        const unsigned meta = simt_cw_node_byte(n, SIMT_CWBVH_OFF_META + s);
        const float qnx = (float)simt_cw_byte(qn[0][s / 4], s % 4);
        const float qfx = (float)simt_cw_byte(qf[0][s / 4], s % 4);
        const float qny = (float)simt_cw_byte(qn[1][s / 4], s % 4);
        const float qfy = (float)simt_cw_byte(qf[1][s / 4], s % 4);
        const float qnz = (float)simt_cw_byte(qn[2][s / 4], s % 4);
        const float qfz = (float)simt_cw_byte(qf[2][s / 4], s % 4);
#ifdef SIMT_PUBLISHED_TESTS
        const float tnx = fmaf(qnx, ax, bx), tfx = fmaf(qfx, ax, bx);
        const float tny = fmaf(qny, ay, by), tfy = fmaf(qfy, ay, by);
        const float tnz = fmaf(qnz, az, bz), tfz = fmaf(qfz, az, bz);
#else
        const float tnx = (fmaf(sx, qnx, px) - r.orig.x) * r.idir.x;
        const float tfx = (fmaf(sx, qfx, px) - r.orig.x) * r.idir.x;
        const float tny = (fmaf(sy, qny, py) - r.orig.y) * r.idir.y;
        const float tfy = (fmaf(sy, qfy, py) - r.orig.y) * r.idir.y;
        const float tnz = (fmaf(sz, qnz, pz) - r.orig.z) * r.idir.z;
        const float tfz = (fmaf(sz, qfz, pz) - r.orig.z) * r.idir.z;
#endif
        const float tn = fmaxf(fmaxf(tnx, tny), fmaxf(tnz, r.tmin));
        const float tf = fminf(rounding * fminf(fminf(tfx, tfy), tfz), tmax);
        const bool hit = meta != 0u && tn <= tf;
        const unsigned low = meta & 31u;
        const bool interior = low >= SIMT_CWBVH_INTERIOR_LOW;
        h.node_hits |= (hit && interior) ? 1u << (s ^ octant) : 0u;
        h.tri_hits |= (hit && !interior) ? (meta >> 5) << low : 0u;
    }
    return h;
}
