"""Animation: the bake (AnimationTexture, hierarchy, clip table), the float64 reference, roles, the GPU
animation processor and its accuracy measure."""
