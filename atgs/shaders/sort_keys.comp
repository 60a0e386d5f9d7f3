#version 430
// viewer/gl_sort.py, pass 2: the 16-bit depth keys of viewer.sorting._back_to_front, in place
// of the depths: floor(clamp((zmax - z) scale, 0, 65534)), farthest 0; culled 65535.
// zmax and the scale come from Stats (sort_stats.comp), never from the host.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Words { uint words[]; };  // ordered depth bits in, keys out
layout(std430, binding = 1) readonly buffer Stats { uint stats[4]; };

uniform uint u_count;

const uint CULLED = 0xFFFFFFFFu;

// This invocation's item: dispatches wider than 65535 groups are split over y (gl_sort._run).
uint item_index() {
    return (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x + gl_LocalInvocationID.x;
}

float from_ordered(uint bits) {
    return uintBitsToFloat((bits & 0x80000000u) != 0u ? bits & 0x7FFFFFFFu : ~bits);
}

void main() {
    float zmax = from_ordered(stats[2]);
    float scale = uintBitsToFloat(stats[3]);
    uint i = item_index();
    if (i < u_count) {
        uint bits = words[i];
        if (bits == CULLED) {
            words[i] = 65535u;
        } else {
            precise float level = (zmax - from_ordered(bits)) * scale;
            words[i] = uint(floor(clamp(level, 0.0, 65534.0)));
        }
    }
}
