#version 330 core
uniform vec3 u_light_dir;
in vec3 v_normal;
in vec4 v_color;
out vec4 frag_color;
void main() {
    vec3 n = normalize(v_normal);
    float diffuse = max(dot(n, -u_light_dir), 0.0);
    float hemi = 0.5 + 0.5 * n.y;
    vec3 c = v_color.rgb * (0.25 + 0.55 * diffuse + 0.25 * hemi);
    frag_color = vec4(pow(c, vec3(1.0 / 2.2)), 1.0);
}
