// Packet traversal (Guenther et al. 2007) with the semantics of Aila & Laine's packet
// kernel: the 32 rays of a warp share one stack in shared memory and walk the tree
// together. Every lane with a ray tests every popped node, an any-hit lane that has its
// hit too (against that hit's t: it keeps taking part in node tests and votes). A child is
// visited when any lane's ray hits its box; when both are, child 1 goes first when more
// than half of the warp's 32 lanes prefer it. Every lane takes part in every leaf: the
// triangle loop runs over all its triangles, and the lanes still searching test them.
//
// Built twice (kernels_ir.build.VARIANTS). `packet` counts the order vote with a warp
// ballot. With SIMT_SHARED_VOTE it is `packet_shared_vote`, the same kernel as a GPU
// without a ballot runs it: GT200 (compute capability 1.3, the paper's GTX 285) votes only
// with __any and __all; __ballot and __popc came with Fermi (2.0). Its order vote is a sum
// in shared memory, each lane adding its partner's partial sum at distances 16, 8, 4, 2
// and 1 until every lane holds the total (Aila & Laine's packet kernel sums its order vote
// in shared memory too), and its child votes are __any. GT200's lanes run in lockstep, so
// the steps need no barrier: that build is a cost model of that hardware's code, compiled
// by today's nvcc and costed, never launched (a Volta or later GPU runs `packet`).
// Launch: blockDim.x a multiple of 32, dynamic shared memory
// (blockDim.x / 32) * SIMT_STACK_SIZE * 4 bytes (the shared vote: SIMT_STACK_SIZE + 32
// ints per warp). any_hit != 0: a lane stops testing triangles at its first hit; the warp
// stops after the leaf where every lane has one.
#include "common.cuh"

#ifdef SIMT_SHARED_VOTE
constexpr bool kSharedVote = true;
extern "C" __global__ void packet_shared_vote(const float4* __restrict__ nodes,
                                              const float4* __restrict__ woop,
                                              const int* __restrict__ tri_index, int root,
                                              const float4* __restrict__ ray_o,
                                              const float4* __restrict__ ray_d, int num_rays,
                                              int any_hit, int* __restrict__ hit_tri,
                                              float* __restrict__ hit_t)
#else
constexpr bool kSharedVote = false;
extern "C" __global__ void packet(const float4* __restrict__ nodes,
                                  const float4* __restrict__ woop,
                                  const int* __restrict__ tri_index, int root,
                                  const float4* __restrict__ ray_o,
                                  const float4* __restrict__ ray_d, int num_rays, int any_hit,
                                  int* __restrict__ hit_tri, float* __restrict__ hit_t)
#endif
{
    // @block ray_setup
    extern __shared__ int simt_packet_stacks[];
    constexpr int kWarpInts = SIMT_STACK_SIZE + (kSharedVote ? SIMT_WARP_SIZE : 0);
    int* stack = simt_packet_stacks + (threadIdx.x / SIMT_WARP_SIZE) * kWarpInts;
    volatile int* votes = stack + SIMT_STACK_SIZE;  // the shared vote's sum
    const int ray = blockIdx.x * blockDim.x + threadIdx.x;
    if (ray - (int)simt_lane_id() >= num_rays) return;  // the whole warp has no ray
    const bool active = ray < num_rays;
    const Ray r = simt_load_ray(ray_o, ray_d, active ? ray : num_rays - 1);
    bool live = active;  // false: the lane has no ray, or (any hit) has its hit
    int sp = 0;          // warp-uniform
    if (simt_lane_id() == 0) stack[0] = SIMT_SENTINEL;
    __syncwarp();
    int node = root;     // warp-uniform
    int hit_addr = -1;
    float t_best = r.tmax;
    // @block loop_control
#pragma unroll 1
    while (node != SIMT_SENTINEL) {
        // @block trav_step
        if (simt_is_interior(node)) {
            const NodeHit h = simt_intersect_node(nodes, node, r, active ? t_best : -SIMT_INF);
            // the lanes whose ray hits each child (the shared vote: whether any lane's does)
            unsigned m0, m1;
            if constexpr (kSharedVote) {
                m0 = __any_sync(SIMT_FULL_MASK, h.hit0);
                m1 = __any_sync(SIMT_FULL_MASK, h.hit1);
            } else {
                m0 = __ballot_sync(SIMT_FULL_MASK, h.hit0);
                m1 = __ballot_sync(SIMT_FULL_MASK, h.hit1);
            }
            if (m0 != 0u && m1 != 0u) {
                // @block trav_both
                const bool first1 = h.hit1 && (!h.hit0 || h.c1min < h.c0min);
                int votes1;
                if constexpr (kSharedVote) {
                    const int lane = simt_lane_id();
                    votes1 = first1 ? 1 : 0;  // lanes in lockstep: no barrier between steps
                    votes[lane] = votes1;
#pragma unroll
                    for (int k = SIMT_WARP_SIZE / 2; k > 0; k /= 2) {
                        votes1 += votes[lane ^ k];
                        votes[lane] = votes1;
                    }
                } else {
                    votes1 = __popc(__ballot_sync(SIMT_FULL_MASK, first1));
                }
                const bool swap = 2 * votes1 > SIMT_WARP_SIZE;
                node = swap ? h.child1 : h.child0;
                ++sp;
                if (simt_lane_id() == 0) stack[sp] = swap ? h.child0 : h.child1;
                __syncwarp();
                // @block trav_step
            } else {
                // @block trav_else
                if ((m0 | m1) != 0u) {
                    // @block trav_one
                    node = m0 != 0u ? h.child0 : h.child1;
                    // @block trav_else
                } else {
                    // @block trav_none
                    node = stack[sp--];
                    // @block trav_else
                }
                // @block trav_step
            }
        } else {
            // @block leaf_entry
            int tri = ~node;
            node = stack[sp--];
            // @block tri_test
#pragma unroll 1
            for (;; tri += 3) {
                const float4 w0 = __ldg(woop + tri);
                if (simt_is_tri_end(w0)) break;
                SimtWoop s;
                bool hit = simt_woop_t(w0, r, live ? t_best : -SIMT_INF, &s);
                if (hit) {
                    // @block tri_u
                    hit = simt_woop_u(woop, tri, w0, r, &s);
                    if (hit) {
                        // @block tri_v
                        hit = simt_woop_v(woop, tri, r, &s);
                        // @block tri_u
                    }
                    // @block tri_test
                }
                const float t = s.t;
                // @block tri_hit
                if (hit) {
                    t_best = t;
                    hit_addr = tri;
                    live = !simt_opaque(any_hit);
                }
                // @block tri_test
            }
            // @block leaf_entry
            if (!__any_sync(SIMT_FULL_MASK, live)) node = SIMT_SENTINEL;
        }
        // @block loop_control
    }
    // @block finish
    if (active) simt_store_hit(tri_index, hit_tri, hit_t, ray, hit_addr, t_best);
    // @end
}
