// Shared device code of the simt-sim traversal kernels.
//
// Byte contract (see simt_sim/bvh/layout.py):
//   nodes : float4[4 * n_nodes]; node i is nodes[4i .. 4i+3]:
//           n0 = (c0.lo.x, c0.hi.x, c0.lo.y, c0.hi.y)
//           n1 = (c1.lo.x, c1.hi.x, c1.lo.y, c1.hi.y)
//           n2 = (c0.lo.z, c0.hi.z, c1.lo.z, c1.hi.z)
//           n3 = (child0, child1, 0, 0) as int bits; child < 0 is a leaf whose triangles
//                start at float4 ~child of woop.
//   woop  : float4[], 3 float4 per triangle (Woop's affine form), each leaf's list ends
//           with a float4 whose x has the bit pattern 0x80000000.
//   tri_index : int[], scene triangle stored at woop float4 j.
//   rays  : ray_o[i] = (origin.xyz, tmin), ray_d[i] = (direction.xyz, tmax); t is in units
//           of |direction|.
//   root  : kernel argument, 0 or ~leaf_start when the whole scene is one leaf.
//
// Every helper is __forceinline__, so its SASS is attributed (through the inline line
// table) to the line of the kernel that calls it, inside that kernel's marked blocks.
//
// Built with -DSIMT_PUBLISHED_TESTS (the "published" tests of kernels_ir), the box and
// triangle tests are the arithmetic of Aila & Laine's released kernels instead of the
// watertight ones: slabs as one FFMA, lo * idir - orig * idir, with no rounding bound on
// tfar, and Woop's test against u >= 0, v >= 0, u + v <= 1. That is what the published
// measurements ran, so their bound is judged with it; it can miss a ray that grazes an
// edge or a box face, which the watertight tests never do.
#pragma once

#define SIMT_STACK_SIZE 64              // per-ray traversal stack (BVH depth must be < 64)
#define SIMT_SENTINEL 0x76543210        // bottom-of-stack marker, larger than any node index
#define SIMT_TRI_END 0x80000000u        // bit pattern of the x of a leaf's end marker
#define SIMT_FULL_MASK 0xffffffffu
#define SIMT_WARP_SIZE 32
#define SIMT_DYNAMIC_FETCH_THRESHOLD 20 // dynamic fetch refills when fewer lanes are active
#define SIMT_INF __int_as_float(0x7f800000)
#define SIMT_OOEPS 0x1p-80f             // 2^-80: smallest |d_i| relative to max |d_j|
#define SIMT_MIN_NORMAL 0x1p-126f       // 2^-126: the clamp never goes below it
#define SIMT_BOX_ROUNDING 0x1.000008p+0f // 1 + 2^-21 >= 1 + 2 gamma_3 (Ize 2013) on tfar
#define SIMT_TRI_ROUNDING 0x1.4p-22f    // 5 * 2^-24: factor of the Woop test's error bounds

// A ray prepared for slab tests: idir = 1 / clamped direction. Slab bounds are
// (lo - orig) * idir, as simt_sim/bvh/geometry.py computes them: with a finite idir no
// inf - inf or 0 * inf appears (Aila & Laine's one-FFMA lo * idir - orig * idir can).
struct Ray {
    float3 orig;
    float3 dir;
    float3 idir;
#ifdef SIMT_PUBLISHED_TESTS
    float3 oidir;  // orig * idir: a slab bound is one FFMA, lo * idir - oidir
#endif
    float tmin;
    float tmax;
};

// Outcome of one traversal step: both child boxes tested against [tmin, tmax].
struct NodeHit {
    int child0;
    int child1;
    float c0min;
    float c1min;
    bool hit0;
    bool hit1;
};

// Approximate reciprocal (one MUFU.RCP): IEEE division would add a slow-path
// subroutine whose instructions the line table charges to the ray setup block.
__device__ __forceinline__ float simt_rcp(float x)
{
    float r;
    asm("rcp.approx.ftz.f32 %0, %1;" : "=f"(r) : "f"(x));
    return r;
}

// The value of x, hidden from the optimiser (no instruction is emitted). Testing a kernel
// argument such as any_hit through it inside the loop keeps the compiler from unswitching
// the loop on that argument, which would duplicate the traversal code and double the
// static counts of its blocks.
__device__ __forceinline__ int simt_opaque(int x)
{
    asm volatile("" : "+r"(x));
    return x;
}

__device__ __forceinline__ Ray simt_make_ray(float4 o, float4 d)
{
    // |d_i| clamped to 2^-80 of the largest component (and 2^-126), keeping 1/d finite
    // and tilting a short direction no more than a long one (simt_sim.bvh.geometry).
    const float ooeps = fmaxf(fmaxf(fmaxf(fabsf(d.x), fabsf(d.y)), fabsf(d.z)) * SIMT_OOEPS,
                              SIMT_MIN_NORMAL);
    Ray r;
    r.orig = make_float3(o.x, o.y, o.z);
    r.dir = make_float3(d.x, d.y, d.z);
    r.idir.x = simt_rcp(fabsf(d.x) > ooeps ? d.x : copysignf(ooeps, d.x));
    r.idir.y = simt_rcp(fabsf(d.y) > ooeps ? d.y : copysignf(ooeps, d.y));
    r.idir.z = simt_rcp(fabsf(d.z) > ooeps ? d.z : copysignf(ooeps, d.z));
#ifdef SIMT_PUBLISHED_TESTS
    r.oidir = make_float3(o.x * r.idir.x, o.y * r.idir.y, o.z * r.idir.z);
#endif
    r.tmin = o.w;
    r.tmax = d.w;
    return r;
}

__device__ __forceinline__ Ray simt_load_ray(const float4* __restrict__ ray_o,
                                             const float4* __restrict__ ray_d, int i)
{
    return simt_make_ray(__ldg(ray_o + i), __ldg(ray_d + i));
}

__device__ __forceinline__ bool simt_is_interior(int node)
{
    // negative (leaf) indices are huge as unsigned, and so is nothing below the sentinel
    return (unsigned)node < (unsigned)SIMT_SENTINEL;
}

// Fetch node `node` and intersect both child boxes with [r.tmin, tmax].
__device__ __forceinline__ NodeHit simt_intersect_node(const float4* __restrict__ nodes,
                                                       int node, const Ray& r, float tmax)
{
    const float4 n0 = __ldg(nodes + 4 * node + 0);
    const float4 n1 = __ldg(nodes + 4 * node + 1);
    const float4 n2 = __ldg(nodes + 4 * node + 2);
    const float4 n3 = __ldg(nodes + 4 * node + 3);
#ifdef SIMT_PUBLISHED_TESTS
    const float c0lox = fmaf(n0.x, r.idir.x, -r.oidir.x);
    const float c0hix = fmaf(n0.y, r.idir.x, -r.oidir.x);
    const float c0loy = fmaf(n0.z, r.idir.y, -r.oidir.y);
    const float c0hiy = fmaf(n0.w, r.idir.y, -r.oidir.y);
    const float c0loz = fmaf(n2.x, r.idir.z, -r.oidir.z);
    const float c0hiz = fmaf(n2.y, r.idir.z, -r.oidir.z);
    const float c1lox = fmaf(n1.x, r.idir.x, -r.oidir.x);
    const float c1hix = fmaf(n1.y, r.idir.x, -r.oidir.x);
    const float c1loy = fmaf(n1.z, r.idir.y, -r.oidir.y);
    const float c1hiy = fmaf(n1.w, r.idir.y, -r.oidir.y);
    const float c1loz = fmaf(n2.z, r.idir.z, -r.oidir.z);
    const float c1hiz = fmaf(n2.w, r.idir.z, -r.oidir.z);
#else
    const float c0lox = (n0.x - r.orig.x) * r.idir.x;
    const float c0hix = (n0.y - r.orig.x) * r.idir.x;
    const float c0loy = (n0.z - r.orig.y) * r.idir.y;
    const float c0hiy = (n0.w - r.orig.y) * r.idir.y;
    const float c0loz = (n2.x - r.orig.z) * r.idir.z;
    const float c0hiz = (n2.y - r.orig.z) * r.idir.z;
    const float c1lox = (n1.x - r.orig.x) * r.idir.x;
    const float c1hix = (n1.y - r.orig.x) * r.idir.x;
    const float c1loy = (n1.z - r.orig.y) * r.idir.y;
    const float c1hiy = (n1.w - r.orig.y) * r.idir.y;
    const float c1loz = (n2.z - r.orig.z) * r.idir.z;
    const float c1hiz = (n2.w - r.orig.z) * r.idir.z;
#endif
    // Watertight, tfar carries the slabs' rounding bound, so a ray touching a box never
    // misses it (as simt_sim.bvh.geometry.node_child_intervals).
#ifdef SIMT_PUBLISHED_TESTS
    const float rounding = 1.0f;
#else
    const float rounding = SIMT_BOX_ROUNDING;
#endif
    NodeHit h;
    h.c0min = fmaxf(fmaxf(fminf(c0lox, c0hix), fminf(c0loy, c0hiy)),
                    fmaxf(fminf(c0loz, c0hiz), r.tmin));
    const float c0max =
        fminf(rounding * fminf(fminf(fmaxf(c0lox, c0hix), fmaxf(c0loy, c0hiy)),
                               fmaxf(c0loz, c0hiz)),
              tmax);
    h.c1min = fmaxf(fmaxf(fminf(c1lox, c1hix), fminf(c1loy, c1hiy)),
                    fmaxf(fminf(c1loz, c1hiz), r.tmin));
    const float c1max =
        fminf(rounding * fminf(fminf(fmaxf(c1lox, c1hix), fmaxf(c1loy, c1hiy)),
                               fmaxf(c1loz, c1hiz)),
              tmax);
    h.hit0 = c0max >= h.c0min;
    h.hit1 = c1max >= h.c1min;
    h.child0 = __float_as_int(n3.x);
    h.child1 = __float_as_int(n3.y);
    return h;
}

__device__ __forceinline__ bool simt_is_tri_end(float4 w0)
{
    return __float_as_uint(w0.x) == SIMT_TRI_END;
}

// Woop test of the triangle at float4 `tri` whose first float4 `w0` is already loaded, in
// its three stages (simt_sim.bvh.geometry.woop_test): t from w0, then u from w1, then v
// from w2, each run only where the one before passed. A kernel calls each stage on a line of
// its own block (tri_test, tri_u, tri_v) so the IR charges a stage only to the lanes, and
// the warps, that reach it. Watertight (the default), a hit needs tmin < t < tmax and
// (u, v) inside the triangle up to their rounding-error bounds eu, ev: u >= -eu, v >= -ev,
// u + v <= 1 + eu + ev (the bounds and their derivation: simt_sim.bvh.geometry).
struct SimtWoop {
    float t, dz, u, eu, px, py, pz, slope;
};

// Stage t: whether tmin < t < tmax; fills s->t (the hit's t when the later stages pass).
__device__ __forceinline__ bool simt_woop_t(float4 w0, const Ray& r, float tmax, SimtWoop* s)
{
    const float oz = w0.w - r.orig.x * w0.x - r.orig.y * w0.y - r.orig.z * w0.z;
    s->dz = r.dir.x * w0.x + r.dir.y * w0.y + r.dir.z * w0.z;
    s->t = oz * simt_rcp(s->dz);
    return s->t > r.tmin && s->t < tmax;
}

// Stage u, after a t in range: whether u is inside.
__device__ __forceinline__ bool simt_woop_u(const float4* __restrict__ woop, int tri, float4 w0,
                                            const Ray& r, SimtWoop* s)
{
    const float4 w1 = __ldg(woop + tri + 1);
    const float ox = w1.w + r.orig.x * w1.x + r.orig.y * w1.y + r.orig.z * w1.z;
    const float dx = r.dir.x * w1.x + r.dir.y * w1.y + r.dir.z * w1.z;
    s->u = ox + s->t * dx;
#ifdef SIMT_PUBLISHED_TESTS
    (void)w0;
    return s->u >= 0.0f;
#else
    // per axis |o_i| + 2 |t d_i|; slope: the error of t over |D.w0|
    const float t2 = fabsf(s->t + s->t);
    s->px = fabsf(r.orig.x) + t2 * fabsf(r.dir.x);
    s->py = fabsf(r.orig.y) + t2 * fabsf(r.dir.y);
    s->pz = fabsf(r.orig.z) + t2 * fabsf(r.dir.z);
    s->slope = (fabsf(w0.w) + s->px * fabsf(w0.x) + s->py * fabsf(w0.y) + s->pz * fabsf(w0.z)) *
               simt_rcp(fabsf(s->dz));
    s->eu = SIMT_TRI_ROUNDING *
            ((fabsf(w1.w) + s->px * fabsf(w1.x) + s->py * fabsf(w1.y) + s->pz * fabsf(w1.z)) +
             (0.5f * fabsf(s->u) + s->slope * fabsf(dx)));
    return s->u >= -s->eu;
#endif
}

// Stage v, after a u inside: whether the triangle is hit (at s->t).
__device__ __forceinline__ bool simt_woop_v(const float4* __restrict__ woop, int tri,
                                            const Ray& r, const SimtWoop* s)
{
    const float4 w2 = __ldg(woop + tri + 2);
    const float oy = w2.w + r.orig.x * w2.x + r.orig.y * w2.y + r.orig.z * w2.z;
    const float dy = r.dir.x * w2.x + r.dir.y * w2.y + r.dir.z * w2.z;
    const float v = oy + s->t * dy;
#ifdef SIMT_PUBLISHED_TESTS
    return v >= 0.0f && s->u + v <= 1.0f;
#else
    const float ev =
        SIMT_TRI_ROUNDING *
        ((fabsf(w2.w) + s->px * fabsf(w2.x) + s->py * fabsf(w2.y) + s->pz * fabsf(w2.z)) +
         (0.5f * fabsf(v) + s->slope * fabsf(dy)));
    return v >= -ev && s->u + v <= 1.0f + (s->eu + ev);
#endif
}

// Result of a trace kernel: scene triangle index (-1: miss) and t (inf: miss).
__device__ __forceinline__ void simt_store_hit(const int* __restrict__ tri_index,
                                               int* __restrict__ hit_tri,
                                               float* __restrict__ hit_t, int ray, int hit_addr,
                                               float t)
{
    hit_tri[ray] = hit_addr >= 0 ? __ldg(tri_index + hit_addr) : -1;
    hit_t[ray] = hit_addr >= 0 ? t : SIMT_INF;
}

__device__ __forceinline__ unsigned simt_lane_id()
{
    return threadIdx.x & (SIMT_WARP_SIZE - 1);
}

__device__ __forceinline__ unsigned simt_lanemask_lt()
{
    return (1u << simt_lane_id()) - 1u;
}

// Warp-aggregated atomic: the lanes of `want` (a subset of `mask`) take __popc(want)
// consecutive slots of `*counter` with one atomicAdd issued by the lowest lane of `want`.
// Every lane of `mask` must call this; all get the first slot back (lane i of `want`
// owns slot base + __popc(want & simt_lanemask_lt())).
__device__ __forceinline__ int simt_warp_fetch_add(int* counter, unsigned want, unsigned mask)
{
    const int leader = __ffs(want) - 1;
    int base = 0;
    if ((int)simt_lane_id() == leader) base = atomicAdd(counter, __popc(want));
    return __shfl_sync(mask, base, leader);
}

// ---------------------------------------------------------------- path tracing helpers

// Parallelogram area light: points corner + a * edge1 + b * edge2, a, b in [0, 1),
// emitting `emission` (radiance) on the side edge1 x edge2 points to. 12 floats.
struct AreaLight {
    float3 corner;
    float3 edge1;
    float3 edge2;
    float3 emission;
};

// Path state kept per path between bounces (wavefront: in global memory).
struct PathVertex {
    float3 pos;
    float3 normal;  // geometric, facing the incoming ray
};

__device__ __forceinline__ unsigned simt_hash(unsigned x)
{
    x ^= x >> 16;
    x *= 0x7feb352du;
    x ^= x >> 15;
    x *= 0x846ca68bu;
    x ^= x >> 16;
    return x;
}

// Uniform float in [0, 1) from a 32-bit xorshift state (never 0).
__device__ __forceinline__ float simt_rand(unsigned& state)
{
    state ^= state << 13;
    state ^= state >> 17;
    state ^= state << 5;
    return (float)(state >> 8) * 5.9604645e-8f;  // 2^-24
}

__device__ __forceinline__ unsigned simt_rng_init(int path, unsigned seed)
{
    return simt_hash((unsigned)path * 0x9e3779b9u ^ simt_hash(seed)) | 1u;
}

__device__ __forceinline__ float3 simt_f3(float4 v) { return make_float3(v.x, v.y, v.z); }

__device__ __forceinline__ float simt_dot(float3 a, float3 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

__device__ __forceinline__ float3 simt_cross(float3 a, float3 b)
{
    return make_float3(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

__device__ __forceinline__ float3 simt_madd(float3 a, float s, float3 b)
{
    return make_float3(a.x + s * b.x, a.y + s * b.y, a.z + s * b.z);
}

// Hit point and geometric normal of the Woop triangle at float4 `addr`: the z row of the
// inverse affine map (w0.xyz) is perpendicular to the triangle's plane.
__device__ __forceinline__ PathVertex simt_hit_vertex(const float4* __restrict__ woop, int addr,
                                                      float4 o, float4 d, float t)
{
    const float4 w0 = __ldg(woop + addr);
    PathVertex pv;
    pv.pos = simt_madd(simt_f3(o), t, simt_f3(d));
    float3 n = simt_f3(w0);
    const float s = rsqrtf(simt_dot(n, n)) * (simt_dot(n, simt_f3(d)) > 0.0f ? -1.0f : 1.0f);
    pv.normal = make_float3(n.x * s, n.y * s, n.z * s);
    return pv;
}

// Cosine-weighted direction around unit normal n (Duff et al.'s branchless basis).
__device__ __forceinline__ float3 simt_sample_cosine(float3 n, float u1, float u2)
{
    const float sign = copysignf(1.0f, n.z);
    const float a = -simt_rcp(sign + n.z);
    const float b = n.x * n.y * a;
    const float3 t = make_float3(1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x);
    const float3 bt = make_float3(b, sign + n.y * n.y * a, -n.y);
    const float r2 = u1;
    const float r = r2 * rsqrtf(fmaxf(r2, 1e-30f));
    const float phi = 6.2831853f * u2;
    const float x = r * __cosf(phi);
    const float y = r * __sinf(phi);
    const float z = (1.0f - r2) * rsqrtf(fmaxf(1.0f - r2, 1e-30f));
    return make_float3(x * t.x + y * bt.x + z * n.x, x * t.y + y * bt.y + z * n.y,
                       x * t.z + y * bt.z + z * n.z);
}

// Next-event estimation: a shadow ray from the hit point to a uniform point of the light
// (direction unnormalised, t in (eps', 1 - 1e-4)) and the radiance it carries if
// unoccluded: albedo/pi * Le * cos_s * cos_l * area / dist^2 * throughput.
// Returns false when the light point is behind the surface or the light faces away.
__device__ __forceinline__ bool simt_sample_light(const AreaLight& light, const PathVertex& pv,
                                                  float3 throughput, float albedo, float eps,
                                                  float u1, float u2, float4* shadow_o,
                                                  float4* shadow_d, float3* contrib)
{
    const float3 lp = simt_madd(simt_madd(light.corner, u1, light.edge1), u2, light.edge2);
    const float3 d = make_float3(lp.x - pv.pos.x, lp.y - pv.pos.y, lp.z - pv.pos.z);
    const float3 ln = simt_cross(light.edge1, light.edge2);  // |ln| = area
    const float dist2 = simt_dot(d, d);
    const float cs = simt_dot(pv.normal, d);
    const float cl = -simt_dot(ln, d);
    if (cs <= 0.0f || cl <= 0.0f) return false;
    const float g = albedo * 0.31830988f * cs * cl * simt_rcp(dist2 * dist2);
    *contrib = make_float3(throughput.x * light.emission.x * g, throughput.y * light.emission.y * g,
                           throughput.z * light.emission.z * g);
    *shadow_o = make_float4(pv.pos.x, pv.pos.y, pv.pos.z, eps * rsqrtf(dist2));
    *shadow_d = make_float4(d.x, d.y, d.z, 1.0f - 1e-4f);
    return true;
}

// Russian roulette after bounce 2: survive with p = min(max throughput, 0.95), reweight.
__device__ __forceinline__ bool simt_roulette(int bounce, float3* throughput, float u)
{
    if (bounce < 2) return true;
    const float p = fminf(fmaxf(fmaxf(throughput->x, throughput->y), throughput->z), 0.95f);
    if (u >= p) return false;
    const float s = simt_rcp(p);
    *throughput = make_float3(throughput->x * s, throughput->y * s, throughput->z * s);
    return true;
}
