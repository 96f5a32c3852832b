// The animated face: the field is linear in the magnitude, so each vertex is its
// neutral position plus the magnitude times its displacement, computed here on the GPU.
attribute vec3 aNeutral;
attribute vec3 aField;
attribute vec3 aNormalNeutral;
attribute vec3 aNormalMoved;
attribute vec2 aUv;

uniform mat4 uModelView;
uniform mat4 uProjection;
uniform mat3 uNormalMatrix;
uniform float uMagnitude;

varying vec3 vNormal;
varying vec2 vUv;

void main() {
    vec3 position = aNeutral + uMagnitude * aField;
    // Normals are not linear in the magnitude; between the neutral face's and the
    // moved face's (at magnitude 1) a blend is within a degree or two, far cheaper than
    // recomputing them from the neighbours every frame.
    vec3 normal = mix(aNormalNeutral, aNormalMoved, uMagnitude);
    vNormal = uNormalMatrix * normal;
    vUv = aUv;
    gl_Position = uProjection * uModelView * vec4(position, 1.0);
}
