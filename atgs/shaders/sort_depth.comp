#version 430
// viewer/gl_sort.py, pass 1: the cull of viewer.sorting._back_to_front and each Gaussian's
// view depth, one invocation per Gaussian. Writes depth[i] as an order-preserving uint of z
// (CULLED for a culled Gaussian) and accumulates the visible count and depth range in Stats.
// The affine rows are written in the fused-multiply-add order that torch's addmm (MKL sgemm)
// rounds the cull rows in on the CPU; a driver that fuses fma() rounds z and the plane tests
// like it (llvmpipe does not fuse; see viewer/gl_sort.py).
layout(local_size_x = 256) in;

layout(std430, binding = 0) readonly buffer Means { float means[]; };          // x, y, z float32
layout(std430, binding = 1) readonly buffer Scales { float scales[]; };        // x, y, z float32
layout(std430, binding = 2) readonly buffer OpacityRGB { uint opacity_rgb[]; }; // 4 x uint16
layout(std430, binding = 3) writeonly buffer Depths { uint depth[]; };
layout(std430, binding = 4) buffer Stats { uint stats[4]; };  // count, zmin, zmax (ordered uints), scale

uniform uint u_count;
uniform vec4 u_depth_row;      // third row of w2c: z = xyz . mean + w
uniform vec4 u_planes[4];      // frustum tests n . mean + d + c extent > 0 (sorting._cull_planes)
uniform float u_extent_factor; // c
uniform bool u_cull;
uniform float u_near;
uniform uint u_min_opacity;    // smallest stored 16-bit opacity o with float32(o / 65535) >= min_alpha

const uint CULLED = 0xFFFFFFFFu;  // above the ordered bits of every finite float and +inf

shared uint s_count, s_zmin, s_zmax;

// This invocation's item: dispatches wider than 65535 groups are split over y (gl_sort._run).
uint item_index() {
    return (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x + gl_LocalInvocationID.x;
}

// Unsigned integer order = float order (positive: set the sign bit; negative: flip all bits),
// so that atomicMin/atomicMax find the depth range.
uint to_ordered(float z) {
    uint bits = floatBitsToUint(z);
    return (bits & 0x80000000u) != 0u ? ~bits : bits | 0x80000000u;
}

float affine(vec4 row, vec3 m) {
    precise float dot3 = fma(row.z, m.z, fma(row.y, m.y, row.x * m.x));
    precise float value = row.w + dot3;
    return value;
}

void main() {
    if (gl_LocalInvocationIndex == 0u) {
        s_count = 0u;
        s_zmin = CULLED;
        s_zmax = 0u;
    }
    barrier();
    uint i = item_index();
    if (i < u_count) {
        vec3 m = vec3(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);
        float z = affine(u_depth_row, m);
        // the low half of the first word is the opacity (little-endian uint16 pairs)
        bool visible = z > u_near && (opacity_rgb[2u * i] & 0xFFFFu) >= u_min_opacity;
        if (visible && u_cull) {
            vec3 s = vec3(scales[3u * i], scales[3u * i + 1u], scales[3u * i + 2u]);
            float extent = sqrt(dot(s, s));
            float margin = min(min(affine(u_planes[0], m), affine(u_planes[1], m)),
                               min(affine(u_planes[2], m), affine(u_planes[3], m)));
            precise float reach = fma(extent, u_extent_factor, margin);
            visible = reach > 0.0;
        }
        uint bits = visible ? to_ordered(z) : CULLED;
        depth[i] = bits;
        if (visible) {
            atomicAdd(s_count, 1u);
            atomicMin(s_zmin, bits);
            atomicMax(s_zmax, bits);
        }
    }
    barrier();  // one global atomic per work group
    if (gl_LocalInvocationIndex == 0u && s_count > 0u) {
        atomicAdd(stats[0], s_count);
        atomicMin(stats[1], s_zmin);
        atomicMax(stats[2], s_zmax);
    }
}
