// The packet kernel (packet.cu) as a GPU without a warp ballot runs it: GT200 (compute
// capability 1.3, the paper's GTX 285) votes only with __any and __all; __ballot and
// __popc came with Fermi (2.0). So the order vote, which child more than half of the
// warp's 32 lanes prefer, is a sum in shared memory, each lane adding its partner's
// partial sum at distances 16, 8, 4, 2 and 1 until every lane holds the total (Aila &
// Laine's packet kernel sums its order vote in shared memory too), and the child votes
// are __any. GT200's lanes run in lockstep, so the steps need no barrier: this is a cost
// model of that hardware's code, compiled by today's nvcc and costed, never launched (a
// Volta or later GPU runs packet.cu). Everything else is packet.cu's, block for block.
// Launch, were it launched: dynamic shared memory
// (blockDim.x / 32) * (SIMT_STACK_SIZE + 32) * 4 bytes.
#include "common.cuh"

extern "C" __global__ void packet_shared_vote(const float4* __restrict__ nodes,
                                              const float4* __restrict__ woop,
                                              const int* __restrict__ tri_index, int root,
                                              const float4* __restrict__ ray_o,
                                              const float4* __restrict__ ray_d, int num_rays,
                                              int any_hit,
                                              int* __restrict__ hit_tri, float* __restrict__ hit_t)
{
    // @block ray_setup
    extern __shared__ int simt_packet_stacks[];
    const int warp = threadIdx.x / SIMT_WARP_SIZE;
    int* stack = simt_packet_stacks + warp * (SIMT_STACK_SIZE + SIMT_WARP_SIZE);
    volatile int* votes = stack + SIMT_STACK_SIZE;  // the order vote's sum
    const int lane = simt_lane_id();
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
            const bool any0 = __any_sync(SIMT_FULL_MASK, h.hit0);
            const bool any1 = __any_sync(SIMT_FULL_MASK, h.hit1);
            if (any0 && any1) {
                // @block trav_both
                const bool first1 = h.hit1 && (!h.hit0 || h.c1min < h.c0min);
                int sum = first1 ? 1 : 0;  // lanes in lockstep: no barrier between steps
                votes[lane] = sum;
#pragma unroll
                for (int k = SIMT_WARP_SIZE / 2; k > 0; k /= 2) {
                    sum += votes[lane ^ k];
                    votes[lane] = sum;
                }
                const bool swap = 2 * sum > SIMT_WARP_SIZE;
                node = swap ? h.child1 : h.child0;
                ++sp;
                if (simt_lane_id() == 0) stack[sp] = swap ? h.child0 : h.child1;
                __syncwarp();
                // @block trav_step
            } else {
                // @block trav_else
                if (any0 || any1) {
                    // @block trav_one
                    node = any0 ? h.child0 : h.child1;
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
