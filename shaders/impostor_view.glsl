// What an agent's impostor shows and where its quad lies (crowd/draw/impostors.py): shared by the quad's
// vertex shader (impostor.vert.glsl) and the compute splat of the smallest ones (impostor_splat.comp.glsl),
// so both draw the same cells on the same plane. Its processor row starts with its key (the clip and phase
// of its heaviest layer): the impostor shows that clip's two atlas frames around the phase, each from the
// two baked views around the direction it is seen from, relative to the agent's heading, at the nearest
// baked elevation. Needs palette.glsl, vertex_packing.glsl and agent_instance.glsl before it.
uniform sampler2D u_impostor_clips;  // (clips, 2): row 0 (first frame, frames, loop, 0), row 1 the clip's box
uniform sampler2D u_cell_bounds;     // (columns, frames): the cell's covered rectangle (u0, v0, u1, v1), 0 to 1 of the cell
uniform int u_key_offset;   // texels from an agent's key (its first texel) to its joint 0
uniform int u_views;        // views around the up axis, at azimuth 2 pi k / u_views (k = 0 faces the agent's front)
uniform int u_elevations;
uniform float u_elevation[4];  // radians, ascending

struct Impostor {
    ivec4 cells;   // frame * columns + column of the 4 cells: (view 0, frame 0), (1, 0), (0, 1), (1, 1)
    vec2 blend;    // between the views, between the frames
    vec4 box;      // the clip's box at the agent's scale: half width, bottom, height, depth half-range
    vec4 rect;     // the quad's corners in the cell, 0 to 1 (u0, v0, u1, v1): the covered rectangles of the cells shown
    vec3 toward;   // unit, from the agent toward the viewer (the sun in a shadow pass)
    vec3 right;    // the quad's across, horizontal
    vec3 up;       // the quad's up
    vec2 heading;  // cos, sin
};

// Its clip's frames, its box and the direction it is seen from; `toward_sun` for a shadow pass (else the
// camera, which is at the origin: positions are camera-relative).
Impostor impostor_of(Agent agent, bool toward_sun, vec3 sun) {
    Impostor im;
    im.heading = heading_cos_sin(agent.heading);
    float scale = agent.position_scale.w;
    vec4 key = texelFetch(u_palette0, palette_texel(agent.texel) - ivec3(u_key_offset, 0, 0), 0);
    int clip = max(int(key.x), 0);  // -1, the rest pose: the first clip's first frame
    vec4 frames = texelFetch(u_impostor_clips, ivec2(clip, 0), 0);
    im.box = texelFetch(u_impostor_clips, ivec2(clip, 1), 0) * scale;
    int count = int(frames.y);
    float f;
    int f0, f1;
    if (frames.z > 0.5) {  // looping: frames at phases k / count, the last blends into the first
        f = fract(key.x < 0.0 ? 0.0 : key.y) * float(count);
        f0 = min(int(f), count - 1);
        f1 = (f0 + 1) % count;
    } else {
        f = clamp(key.x < 0.0 ? 0.0 : key.y, 0.0, 1.0) * float(count - 1);
        f0 = min(int(f), max(count - 2, 0));
        f1 = min(f0 + 1, count - 1);
    }
    float frame_t = clamp(f - float(f0), 0.0, 1.0);
    im.toward = toward_sun ? sun : normalize(-(agent.position_scale.xyz + vec3(0.0, im.box.y + 0.5 * im.box.z, 0.0)));
    // The direction seen from, in the agent's frame (its heading turned back).
    vec3 m = turn_about_y(vec2(im.heading.x, -im.heading.y), im.toward);
    float azimuth = atan(m.x, m.z) / 6.28318530718 * float(u_views);
    azimuth = azimuth < 0.0 ? azimuth + float(u_views) : azimuth;
    int v0 = int(floor(azimuth)) % u_views;
    int v1 = (v0 + 1) % u_views;
    float elevation = asin(clamp(m.y, -1.0, 1.0));
    int e = 0;
    for (int k = 1; k < u_elevations; ++k) {
        if (abs(elevation - u_elevation[k]) < abs(elevation - u_elevation[e])) e = k;
    }
    int columns = u_views * u_elevations;
    int first = int(frames.x);
    im.cells = ivec4((first + f0) * columns + e * u_views + v0, (first + f0) * columns + e * u_views + v1,
                     (first + f1) * columns + e * u_views + v0, (first + f1) * columns + e * u_views + v1);
    im.blend = vec2(fract(azimuth), frame_t);
    vec3 right = vec3(im.toward.z, 0.0, -im.toward.x);
    im.right = dot(right, right) > 1e-8 ? normalize(right) : vec3(1.0, 0.0, 0.0);
    im.up = cross(im.toward, im.right);
    return im;
}

// Its bound's centre in clip space, for its height on screen.
vec4 impostor_centre(Agent agent, Impostor im, mat4 view_proj) {
    return view_proj * vec4(agent.position_scale.xyz + vec3(0.0, im.box.y + 0.5 * im.box.z, 0.0), 1.0);
}

// Whether it is shorter than `px` pixels on screen (`focal_px`: pixels a metre spans at a metre's depth).
bool impostor_shorter(Impostor im, vec4 centre, float focal_px, float px) {
    return im.box.z * focal_px < px * max(centre.w, 1e-6);
}

// One weight 1, three 0 (their fetches skipped), every cell that one; then the quad's rectangle.
void impostor_nearest(inout Impostor im) {
    im.blend = floor(im.blend + 0.5);
    im.cells = ivec4(im.cells[int(im.blend.x) + 2 * int(im.blend.y)]);
}

// The quad covers the covered rectangles of the cells it shows (of the clip's box, the rest is empty).
void impostor_rect(inout Impostor im) {
    int columns = u_views * u_elevations;
    vec4 rect = vec4(1.0, 1.0, 0.0, 0.0);
    for (int k = 0; k < 4; ++k) {
        if (k > 0 && im.cells[k] == im.cells[0]) continue;
        vec4 b = texelFetch(u_cell_bounds, ivec2(im.cells[k] % columns, im.cells[k] / columns), 0);
        rect = vec4(min(rect.xy, b.xy), max(rect.zw, b.zw));
    }
    im.rect = vec4(rect.xy, max(rect.zw, rect.xy));
}

// The point of the quad's plane at `corner` (x across, y up, 0 to 1 of the clip's box), camera-relative.
vec3 impostor_point(Agent agent, Impostor im, vec2 corner) {
    return agent.position_scale.xyz + im.right * ((2.0 * corner.x - 1.0) * im.box.x) + im.up * (im.box.y + corner.y * im.box.z);
}
