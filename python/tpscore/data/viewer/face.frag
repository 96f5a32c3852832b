// Skin colour from the scan's photograph (or clay without one), lit by a lamp above and
// to the left of the viewer. The photograph already holds the scanner's light, so it
// gets more ambient and less directional light than clay would.
precision mediump float;

uniform sampler2D uTexture;
uniform bool uTextured;
uniform vec3 uLight;

varying vec3 vNormal;
varying vec2 vUv;

void main() {
    vec3 normal = normalize(vNormal);
    if (!gl_FrontFacing) {
        normal = -normal;
    }
    vec3 albedo = uTextured ? texture2D(uTexture, vUv).rgb : vec3(0.86, 0.78, 0.70);
    float diffuse = max(dot(normal, uLight), 0.0);
    vec3 halfway = normalize(uLight + vec3(0.0, 0.0, 1.0));
    float specular = pow(max(dot(normal, halfway), 0.0), 24.0);
    float ambient = uTextured ? 0.5 : 0.2;
    float direct = uTextured ? 0.55 : 0.75;
    gl_FragColor = vec4(albedo * (ambient + direct * diffuse) + 0.05 * specular, 1.0);
}
