"""Drawing: skinned instancing with LOD, culling and shadows, the socket read-back ring and the weapons."""
