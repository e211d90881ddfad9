// One sample of an impostor's atlas (crowd/draw/impostors.py), shared by the quad's fragment shader
// (impostor.frag.glsl) and the compute splat (impostor_splat.comp.glsl). The atlas has no mip levels:
// both read level 0, bilinear.
uniform sampler2DArray u_atlas_albedo;        // RGBA8: albedo, coverage
uniform sampler2DArray u_atlas_normal_depth;  // RGBA8: octahedral normal, depth (16 bits in two channels)
uniform int u_columns;  // cells across a layer: views x elevations
uniform int u_rows;     // frames a layer holds

// Where `corner` (0 to 1 of the clip's box) of a cell lies in the atlas.
vec3 cell_coord(int cell, vec2 corner) {
    int frame = cell / u_columns;
    int column = cell - frame * u_columns;
    int layer = frame / u_rows;
    int row = frame - layer * u_rows;
    return vec3((vec2(float(column), float(row)) + corner) / vec2(float(u_columns), float(u_rows)), float(layer));
}

// The depth a texel holds, 0 to 1 across the clip's depth range (16 bits in two channels: a filtered
// texel decodes linearly, so a sum of weighted texels is the weighted depth).
float atlas_depth(vec4 normal_depth) {
    return (normal_depth.z * (255.0 * 256.0) + normal_depth.w * 255.0) / 65535.0;
}

// The surface point the atlas's depth (0 to 1 across the clip's depth range either side of the quad,
// already divided by the coverage) puts at `on_quad`, a point of the quad's plane.
vec3 atlas_surface(vec3 on_quad, vec3 toward, float depth, float depth_range) {
    return on_quad + toward * ((depth * 2.0 - 1.0) * depth_range);
}

// A camera-relative point's window depth, 0 to 1.
float window_depth(mat4 view_proj, vec3 world) {
    vec4 clip = view_proj * vec4(world, 1.0);
    return clamp(clip.z / clip.w * 0.5 + 0.5, 0.0, 1.0);
}
