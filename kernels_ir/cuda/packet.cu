// Packet traversal (Guenther et al. 2007) with the semantics of Aila & Laine's packet
// kernel: the 32 rays of a warp share one stack in shared memory and walk the tree
// together. Every lane with a ray tests every popped node, an any-hit lane that has its
// hit too (against that hit's t: it keeps taking part in node tests and votes). A child is
// visited when any lane's ray hits its box; when both are, child 1 goes first when more
// than half of the warp's 32 lanes prefer it. Every lane takes part in every leaf: the
// triangle loop runs over all its triangles, and the lanes still searching test them.
// Launch: blockDim.x a multiple of 32, dynamic shared memory
// (blockDim.x / 32) * SIMT_STACK_SIZE * 4 bytes. any_hit != 0: a lane stops testing
// triangles at its first hit; the warp stops after the leaf where every lane has one.
#include "common.cuh"

extern "C" __global__ void packet(const float4* __restrict__ nodes,
                                  const float4* __restrict__ woop,
                                  const int* __restrict__ tri_index, int root,
                                  const float4* __restrict__ ray_o,
                                  const float4* __restrict__ ray_d, int num_rays, int any_hit,
                                  int* __restrict__ hit_tri, float* __restrict__ hit_t)
{
    // @block ray_setup
    extern __shared__ int simt_packet_stacks[];
    int* stack = simt_packet_stacks + (threadIdx.x / SIMT_WARP_SIZE) * SIMT_STACK_SIZE;
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
            const unsigned m0 = __ballot_sync(SIMT_FULL_MASK, h.hit0);
            const unsigned m1 = __ballot_sync(SIMT_FULL_MASK, h.hit1);
            if (m0 != 0u && m1 != 0u) {
                // @block trav_both
                const bool first1 = h.hit1 && (!h.hit0 || h.c1min < h.c0min);
                const unsigned votes1 = __ballot_sync(SIMT_FULL_MASK, first1);
                const bool swap = 2 * __popc(votes1) > SIMT_WARP_SIZE;
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
