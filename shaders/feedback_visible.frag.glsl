#version 410 core
flat in uint v_visible;
out uint visible;

void main() {
    visible = v_visible;
}
