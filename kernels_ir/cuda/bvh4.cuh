// Shared device code of the kernels on the 4-wide BVH layout (bvh4_*.cu).
//
// Byte contract (see simt_sim/bvh/wide.py, layout "bvh4"):
//   nodes : float4[7 * n_nodes], structure of arrays; node i is nodes[7i .. 7i+6], 112 bytes:
//           row 0 lo.x of children 0..3   row 1 hi.x
//           row 2 lo.y                    row 3 hi.y
//           row 4 lo.z                    row 5 hi.z
//           row 6 child index of children 0..3 as int bits: >= 0 a wide interior node,
//                 < 0 a leaf whose triangles start at float4 ~child of woop (as in the
//                 binary layout), SIMT_BVH4_EMPTY an unused slot, whose box is
//                 lo = +inf, hi = -inf.
//   woop, tri_index, rays, root: the binary layout's (common.cuh), byte for byte: the
//           wide tree keeps the binary tree's leaves and Woop triangles.
//
// The child test is the binary kernels' slab arithmetic (simt_intersect_node) with the
// near and far plane of each axis picked once per ray by the sign of the inverse
// direction, as simt_sim/bvh/wide_traverse.py does: for a box with lo <= hi that is
// exactly fminf/fmaxf of the two slab distances, and it keeps an empty slot a miss (both
// of its near distances are +inf, its far ones -inf), which min/max would not.
#pragma once

#include "common.cuh"

#define SIMT_BVH4_WIDTH 4               // children per node
#define SIMT_BVH4_NODE_FLOAT4 7         // float4 rows per node: 112 bytes
#define SIMT_BVH4_LO_X 0                // row of lo.x of the 4 children
#define SIMT_BVH4_HI_X 1
#define SIMT_BVH4_LO_Y 2
#define SIMT_BVH4_HI_Y 3
#define SIMT_BVH4_LO_Z 4
#define SIMT_BVH4_HI_Z 5
#define SIMT_BVH4_CHILD 6               // row of the 4 child indices (int bits)
#define SIMT_BVH4_EMPTY ((int)0x80000000) // child index of an unused slot (INT32_MIN)
// Per-ray stack, sentinel at 0: a node at wide depth d (root 0) is traversed with sp <= 3d,
// and its step writes up to stack[sp + 4] (3 pushes and the scratch slot of
// simt_bvh4_order_push), so interior nodes at depth <= 62 (WideStats.depth < 64) need
// at most 191 entries.
#define SIMT_BVH4_STACK_SIZE (3 * SIMT_STACK_SIZE)

// Pointers to the near and far plane rows of node 0 on each axis for one ray (picked once,
// in ray setup, by the signs of the inverse direction): node i's row is row + 7 * i, one
// IMAD.WIDE per load in the traversal step.
struct Bvh4Planes {
    const float4* near_x;
    const float4* far_x;
    const float4* near_y;
    const float4* far_y;
    const float4* near_z;
    const float4* far_z;
};

// Outcome of one traversal step: the 4 child boxes tested against [tmin, tmax].
struct Bvh4Hit {
    float tnear[SIMT_BVH4_WIDTH];
    int child[SIMT_BVH4_WIDTH];
    bool hit[SIMT_BVH4_WIDTH];
};

// The pointer p, hidden from the optimiser (no instruction is emitted), so that it stays
// a per-ray pointer instead of being folded back into the node index arithmetic (four
// integer instructions per load, a 64-bit add and a shift, instead of one IMAD.WIDE).
__device__ __forceinline__ const float4* simt_opaque_ptr(const float4* p)
{
    asm("" : "+l"(p));
    return p;
}

__device__ __forceinline__ Bvh4Planes simt_bvh4_planes(const float4* __restrict__ nodes,
                                                       const Ray& r)
{
    const bool neg_x = r.idir.x < 0.0f;
    const bool neg_y = r.idir.y < 0.0f;
    const bool neg_z = r.idir.z < 0.0f;
    Bvh4Planes p;
    p.near_x = simt_opaque_ptr(nodes + (neg_x ? SIMT_BVH4_HI_X : SIMT_BVH4_LO_X));
    p.far_x = simt_opaque_ptr(nodes + (neg_x ? SIMT_BVH4_LO_X : SIMT_BVH4_HI_X));
    p.near_y = simt_opaque_ptr(nodes + (neg_y ? SIMT_BVH4_HI_Y : SIMT_BVH4_LO_Y));
    p.far_y = simt_opaque_ptr(nodes + (neg_y ? SIMT_BVH4_LO_Y : SIMT_BVH4_HI_Y));
    p.near_z = simt_opaque_ptr(nodes + (neg_z ? SIMT_BVH4_HI_Z : SIMT_BVH4_LO_Z));
    p.far_z = simt_opaque_ptr(nodes + (neg_z ? SIMT_BVH4_LO_Z : SIMT_BVH4_HI_Z));
    return p;
}

__device__ __forceinline__ float simt_f4_get(float4 v, int i)
{
    return i == 0 ? v.x : (i == 1 ? v.y : (i == 2 ? v.z : v.w));
}

// Slab distance of plane value `plane` on one axis (the binary test's formula).
__device__ __forceinline__ float simt_slab(float plane, float orig, float idir, float oidir)
{
#ifdef SIMT_PUBLISHED_TESTS
    return fmaf(plane, idir, -oidir);
#else
    (void)oidir;
    return (plane - orig) * idir;
#endif
}

// Fetch node `node` (7 float4) and intersect its 4 child boxes with [r.tmin, tmax].
__device__ __forceinline__ Bvh4Hit simt_bvh4_intersect_node(const float4* __restrict__ nodes,
                                                            int node, const Ray& r,
                                                            const Bvh4Planes& p, float tmax)
{
    const int row = SIMT_BVH4_NODE_FLOAT4 * node;
    const float4 nx = __ldg(p.near_x + row);
    const float4 fx = __ldg(p.far_x + row);
    const float4 ny = __ldg(p.near_y + row);
    const float4 fy = __ldg(p.far_y + row);
    const float4 nz = __ldg(p.near_z + row);
    const float4 fz = __ldg(p.far_z + row);
    const float4 ch = __ldg(nodes + row + SIMT_BVH4_CHILD);
#ifdef SIMT_PUBLISHED_TESTS
    const float3 oidir = r.oidir;
    const float rounding = 1.0f;
#else
    const float3 oidir = make_float3(0.0f, 0.0f, 0.0f);
    const float rounding = SIMT_BOX_ROUNDING;
#endif
    Bvh4Hit h;
#pragma unroll
    for (int c = 0; c < SIMT_BVH4_WIDTH; ++c) {
        const float tnx = simt_slab(simt_f4_get(nx, c), r.orig.x, r.idir.x, oidir.x);
        const float tfx = simt_slab(simt_f4_get(fx, c), r.orig.x, r.idir.x, oidir.x);
        const float tny = simt_slab(simt_f4_get(ny, c), r.orig.y, r.idir.y, oidir.y);
        const float tfy = simt_slab(simt_f4_get(fy, c), r.orig.y, r.idir.y, oidir.y);
        const float tnz = simt_slab(simt_f4_get(nz, c), r.orig.z, r.idir.z, oidir.z);
        const float tfz = simt_slab(simt_f4_get(fz, c), r.orig.z, r.idir.z, oidir.z);
        // as simt_intersect_node: watertight, tfar carries the slabs' rounding bound
        const float tn = fmaxf(fmaxf(tnx, tny), fmaxf(tnz, r.tmin));
        const float tf = fminf(rounding * fminf(fminf(tfx, tfy), tfz), tmax);
        h.tnear[c] = tn;
        h.hit[c] = tf >= tn;
        h.child[c] = __float_as_int(simt_f4_get(ch, c));
    }
    return h;
}

// Number of child boxes hit.
__device__ __forceinline__ int simt_bvh4_count(const Bvh4Hit& h)
{
    return (int)h.hit[0] + (int)h.hit[1] + (int)h.hit[2] + (int)h.hit[3];
}

// The one child hit (exactly one of h.hit is set).
__device__ __forceinline__ int simt_bvh4_single(const Bvh4Hit& h)
{
    return h.hit[0] ? h.child[0] : (h.hit[1] ? h.child[1] : (h.hit[2] ? h.child[2] : h.child[3]));
}

// k >= 2 children hit: order them by tnear (ties keep slot order, as the stable insertion
// of wide_traverse.py), return the nearest and push the other k - 1 farthest first, so they
// pop front to back. Each hit child's rank is the number of hit children before it in that
// order; the child of rank j >= 1 goes to stack[sp + k - j]. Branch free, so the cost does
// not depend on k: all 4 children are stored, the nearest and the missed ones to
// stack[sp + k], the first slot above the new top (a later push overwrites it).
__device__ __forceinline__ int simt_bvh4_order_push(const Bvh4Hit& h, int k, int* stack,
                                                    int& sp)
{
    int rank[SIMT_BVH4_WIDTH] = {0, 0, 0, 0};
#pragma unroll
    for (int a = 0; a < SIMT_BVH4_WIDTH; ++a) {
#pragma unroll
        for (int b = a + 1; b < SIMT_BVH4_WIDTH; ++b) {
            const bool b_first = h.tnear[b] < h.tnear[a];  // equal: slot a first
            rank[a] += (h.hit[b] && b_first) ? 1 : 0;
            rank[b] += (h.hit[a] && !b_first) ? 1 : 0;
        }
    }
    const int top = sp + k;
    int next = 0;
#pragma unroll
    for (int c = 0; c < SIMT_BVH4_WIDTH; ++c) {
        const int j = h.hit[c] ? rank[c] : 0;
        stack[top - j] = h.child[c];
        next = (h.hit[c] && j == 0) ? h.child[c] : next;
    }
    sp = top - 1;
    return next;
}
