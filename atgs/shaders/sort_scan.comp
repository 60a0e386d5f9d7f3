#version 430
// viewer/gl_sort.py, radix pass step 2 of 3: exclusive prefix sum, in place, of the digit
// counts, in three dispatches. STAGE 1: each invocation sums a chunk of CHUNK consecutive
// counts into partials[chunk]; STAGE 2: one work group scans the partials in place;
// STAGE 3: each invocation rewrites its chunk as prefixes, starting from its partial.
// Sequential chunks need no barrier (llvmpipe pays dearly for work-group barriers; a GPU
// runs thousands of chunks at once). Integer sums: exact and the same for any scheduling.
layout(local_size_x = 256) in;

layout(std430, binding = 0) buffer Values { uint values[]; };
layout(std430, binding = 1) buffer Partials { uint partials[]; };

uniform uint u_count;  // entries of values

// This invocation's item: dispatches wider than 65535 groups are split over y (gl_sort._run).
uint item_index() {
    return (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x + gl_LocalInvocationID.x;
}

#if STAGE == 2
shared uint s_scan[2][256];

// Exclusive prefix of v over the work group's invocations (Hillis-Steele, ping-ponging
// between two shared rows: one barrier per step).
uint group_exclusive_scan(uint v) {
    uint t = gl_LocalInvocationIndex;
    s_scan[0][t] = v;
    barrier();
    uint row = 0u;
    for (uint step = 1u; step < 256u; step <<= 1u) {
        s_scan[1u - row][t] = s_scan[row][t] + (t >= step ? s_scan[row][t - step] : 0u);
        row = 1u - row;
        barrier();
    }
    return s_scan[row][t] - v;
}
#endif

void main() {
    uint chunks = (u_count + CHUNK - 1u) / CHUNK;
#if STAGE == 2
    // invocation t scans a contiguous run of the partials, offset by the runs before it
    uint run = (chunks + 255u) / 256u;
    uint begin = min(chunks, gl_LocalInvocationIndex * run), end = min(chunks, begin + run);
    uint sum = 0u;
    for (uint c = begin; c < end; ++c) {
        sum += partials[c];
    }
    uint running = group_exclusive_scan(sum);
    for (uint c = begin; c < end; ++c) {
        uint v = partials[c];
        partials[c] = running;
        running += v;
    }
#else
    uint c = item_index();
    if (c < chunks) {
        uint end = min(u_count, (c + 1u) * CHUNK);
#if STAGE == 1
        uint sum = 0u;
        for (uint i = c * CHUNK; i < end; ++i) {
            sum += values[i];
        }
        partials[c] = sum;
#else
        uint running = partials[c];
        for (uint i = c * CHUNK; i < end; ++i) {
            uint v = values[i];
            values[i] = running;
            running += v;
        }
#endif
    }
#endif
}
