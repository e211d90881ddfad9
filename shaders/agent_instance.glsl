// The agent an instance draws (crowd/draw/cull_lists.py): its list entry is the one instanced attribute
// (the agent's index in the low 24 bits, this copy's fade code in the top byte: lod_fade.glsl, 255 for
// none), and its 32-byte record comes from the crowd's record buffer through a buffer texture
// (crowd/draw/records.py), so every list costs 4 bytes an entry and the records are written once.
#ifndef NO_INSTANCE_ENTRY
in uint i_entry;
#endif
uniform usamplerBuffer u_agents;  // two texels a record: (position, scale) as float bits | fields

struct Agent {
    vec4 position_scale;  // origin relative to the camera (float64 on the CPU, then float32), uniform scale
    uint texel;           // palette texel code of joint 0 (palette.glsl)
    vec4 tint;            // RGB (its alpha byte is the agent's character: drawn as 1)
    uint heading;         // cos, sin of the heading, snorm16 x2
    uint fade;            // this copy's fade code
};

// The agent a list entry names (a compute pass reads entries from the lists' buffer itself).
Agent agent_of(uint entry) {
    int record = 2 * int(entry & 0xFFFFFFu);
    uvec4 place = texelFetch(u_agents, record);
    uvec4 fields = texelFetch(u_agents, record + 1);
    Agent a;
    a.position_scale = uintBitsToFloat(place);
    a.texel = fields.x;
    a.tint = vec4(unpack_rgba8(fields.y).rgb, 1.0);
    a.heading = fields.z;
    a.fade = entry >> 24;
    return a;
}

#ifndef NO_INSTANCE_ENTRY
Agent instance_agent() {
    return agent_of(i_entry);
}
#endif
