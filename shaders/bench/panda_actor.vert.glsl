#version 150
// The Panda3D peer of `crowd-bench peers` (bench/peers_panda.py): one Actor per agent, drawn with
// the crowd's own fragment shader (skin.frag.glsl, lighting.glsl) so both sides pay the same per-pixel
// cost; this vertex shader hands it the same inputs.
//
// Why hand-written: under EGL Panda3D's shader generator has no Cg profile, and with
// hardware-animated-vertices on, setShaderAuto() then draws every actor in its bind pose. With
// HARDWARE_SKINNING this shader skins from Panda3D's per-actor transform table instead (the
// ShaderAttrib carries F_hardware_skinning, so Panda3D leaves the vertices alone on the CPU).
// Without it, Panda3D has already animated the vertices on the CPU and they arrive skinned.
//
// Panda3D is Z-up and the shared lighting is Y-up: positions and normals are handed to it in Y-up.

uniform mat4 p3d_ModelViewProjectionMatrix;
uniform mat4 p3d_ModelMatrix;
uniform struct p3d_MaterialParameters { vec4 baseColor; } p3d_Material;
uniform vec3 u_eye;  // camera position in Panda3D's world (Z-up)

in vec4 p3d_Vertex;
in vec3 p3d_Normal;
in vec4 p3d_Color;
#ifdef HARDWARE_SKINNING
uniform mat4 p3d_TransformTable[MAX_TRANSFORMS];
in vec4 transform_weight;
in uvec4 transform_index;
#endif

out vec3 v_world;  // camera-relative, Y-up
out vec3 v_normal;
out vec4 v_color;

void main() {
    vec4 p = p3d_Vertex;
    vec3 n = p3d_Normal;
#ifdef HARDWARE_SKINNING
    mat4 skin = p3d_TransformTable[transform_index.x] * transform_weight.x
              + p3d_TransformTable[transform_index.y] * transform_weight.y
              + p3d_TransformTable[transform_index.z] * transform_weight.z
              + p3d_TransformTable[transform_index.w] * transform_weight.w;
    p = skin * p;
    n = mat3(skin) * n;
#endif
    gl_Position = p3d_ModelViewProjectionMatrix * p;
    vec3 world = (p3d_ModelMatrix * p).xyz - u_eye;
    vec3 normal = mat3(p3d_ModelMatrix) * n;
    v_world = vec3(world.x, world.z, -world.y);
    v_normal = vec3(normal.x, normal.z, -normal.y);
    v_color = p3d_Color * p3d_Material.baseColor;
}
