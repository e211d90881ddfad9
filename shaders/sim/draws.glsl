// The numpy AI's keyed random draws (crowd.sim.spawn.SpawnMixin._draws): splitmix64's finaliser over
// (seed, agent, substep, purpose), in 32-bit halves (GLSL has no 64-bit integers in core). The base of
// a substep and purpose comes from the CPU; a draw is the top 24 bits, the numpy draw's exactly.
uvec2 mul64(uvec2 a, uvec2 b) {  // (low, high) halves, the low 64 bits of the product
    uint hi, lo;
    umulExtended(a.x, b.x, hi, lo);
    return uvec2(lo, hi + a.x * b.y + a.y * b.x);
}

uvec2 add64(uvec2 a, uvec2 b) {
    uint carry;
    uint lo = uaddCarry(a.x, b.x, carry);
    return uvec2(lo, a.y + b.y + carry);
}

uvec2 shr64(uvec2 a, uint k) {  // 0 < k < 32
    return uvec2((a.x >> k) | (a.y << (32u - k)), a.y >> k);
}

// (row + 1) x the golden ratio's 64 bits, for rows 0 to 3: written out, as Mesa's llvmpipe folds a
// umulExtended of two constants wrongly once the product carries into the high word.
const uvec2 ROW_STEP[4] = uvec2[4](uvec2(0x7F4A7C15u, 0x9E3779B9u), uvec2(0xFE94F82Au, 0x3C6EF372u),
                                   uvec2(0x7DDF743Fu, 0xDAA66D2Cu), uvec2(0xFD29F054u, 0x78DDE6E5u));
const uvec2 MIX1 = uvec2(0x1CE4E5B9u, 0xBF58476Du);
const uvec2 MIX2 = uvec2(0x133111EBu, 0x94D049BBu);

uint keyed_bits(uvec2 base, uint agent, uint row) {  // row < 4: the draw's 24 bits
    uvec2 key = mul64(uvec2(agent, 0u), MIX1) ^ base;
    uvec2 z = add64(key, ROW_STEP[row]);
    z ^= shr64(z, 30u);
    z = mul64(z, MIX1);
    z ^= shr64(z, 27u);
    z = mul64(z, MIX2);
    z ^= shr64(z, 31u);
    return z.y >> 8u;
}

float keyed_draw(uvec2 base, uint agent, uint row) {
    return float(keyed_bits(base, agent, row)) * (1.0 / 16777216.0);
}

int keyed_pick(uvec2 base, uint agent, uint row, int count) {  // floor(draw x count), in integers (crowd.sim.spawn.draw_pick)
    uint hi, lo;
    umulExtended(keyed_bits(base, agent, row), uint(count), hi, lo);
    return int((hi << 8) | (lo >> 24));
}
