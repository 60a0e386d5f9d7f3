#version 430
// viewer/gl_sort.py, radix pass step 1 of 3: per block of BLOCK_SIZE consecutive items, the
// count of each 8-bit digit (key >> u_shift) & 255, stored digit-major (counts[d * blocks + b])
// so that one exclusive scan over it gives every block's first slot for every digit.
// One invocation walks one block (see the module docstring for the choice of BLOCK_SIZE).
// INPUT_PAIRS 0: the keys array (the item's index is its position); 1: (key, index) pairs.
layout(local_size_x = 64) in;

#if INPUT_PAIRS
layout(std430, binding = 0) readonly buffer Items { uvec2 items[]; };
#define KEY(i) items[i].x
#else
layout(std430, binding = 0) readonly buffer Keys { uint keys[]; };
#define KEY(i) keys[i]
#endif
layout(std430, binding = 1) writeonly buffer Counts { uint counts[]; };

uniform uint u_count;
uniform uint u_blocks;
uniform uint u_shift;

// This invocation's item: dispatches wider than 65535 groups are split over y (gl_sort._run).
uint item_index() {
    return (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x + gl_LocalInvocationID.x;
}

void main() {
    uint b = item_index();
    if (b < u_blocks) {
        uint histogram[256];
        for (uint d = 0u; d < 256u; ++d) {
            histogram[d] = 0u;
        }
        uint end = min(u_count, (b + 1u) * BLOCK_SIZE);
        for (uint i = b * BLOCK_SIZE; i < end; ++i) {
            histogram[(KEY(i) >> u_shift) & 255u] += 1u;
        }
        for (uint d = 0u; d < 256u; ++d) {
            counts[d * u_blocks + b] = histogram[d];
        }
    }
}
