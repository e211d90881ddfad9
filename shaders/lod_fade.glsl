// LOD cross-fades (crowd/draw/render.py, LOD_FADE): an agent within a fade band past a LOD switch is drawn
// at both LODs, and each copy keeps the pixels the other leaves, by a screen-space dither. The band's
// code rides in the top byte of the copy's list entry (shaders/agent_instance.glsl): 255 for no fade;
// else bit 7 says which side (0: the finer LOD, fading out; 1: the coarser, fading in) and bits 0-6 how
// far through the band the agent is (0 at the switch, 127 at its end).
float fade_dither(vec2 pixel) {  // interleaved gradient noise (Jimenez 2014): even over any small block of pixels
    return fract(52.9829189 * fract(dot(pixel, vec2(0.06711056, 0.00583715))));
}

bool faded_out(uint code, vec2 pixel) {
    if (code == 255u) return false;
    float through = float(code & 127u) / 127.0;
    float d = fade_dither(pixel);
    return code >= 128u ? d >= through : d < through;
}
