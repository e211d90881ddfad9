"""Import: a Character (skeleton parents-first, skinned pieces per LOD, clips, props) from glTF or from the
built-in zombie generator, and the glTF writer. Below every other stage."""
