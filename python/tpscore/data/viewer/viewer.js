// tpscore's result page: the animated target face, drawn with WebGL. Everything it
// needs is in the page: the neutral face, the displacement field, the normals, the u,v
// map and the photograph, as base64 in the "face-data" element.
(function () {
  "use strict";

  var canvas = document.getElementById("face");
  var slider = document.getElementById("magnitude");
  var valueText = document.getElementById("magnitude-value");
  var play = document.getElementById("play");
  var errorBox = document.getElementById("error");
  var state = { ready: false, frames: 0, magnitude: parseFloat(slider.value) };
  window.tpscoreViewer = state;

  function fail(message) {
    errorBox.textContent = message;
    console.error("tpscore viewer: " + message);
  }

  // ------------------------------------------------------------------ 4 x 4 matrices
  // Column-major, as WebGL reads them.

  function multiply(a, b) {
    var out = new Float32Array(16);
    for (var column = 0; column < 4; column++) {
      for (var row = 0; row < 4; row++) {
        var sum = 0;
        for (var k = 0; k < 4; k++) {
          sum += a[k * 4 + row] * b[column * 4 + k];
        }
        out[column * 4 + row] = sum;
      }
    }
    return out;
  }

  function translation(x, y, z) {
    return new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, x, y, z, 1]);
  }

  function rotationX(angle) {
    var c = Math.cos(angle), s = Math.sin(angle);
    return new Float32Array([1, 0, 0, 0, 0, c, s, 0, 0, -s, c, 0, 0, 0, 0, 1]);
  }

  function rotationY(angle) {
    var c = Math.cos(angle), s = Math.sin(angle);
    return new Float32Array([c, 0, -s, 0, 0, 1, 0, 0, s, 0, c, 0, 0, 0, 0, 1]);
  }

  function perspective(fieldOfView, aspect, near, far) {
    var f = 1 / Math.tan(fieldOfView / 2);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0,
                             0, 0, (far + near) / (near - far), -1,
                             0, 0, 2 * far * near / (near - far), 0]);
  }

  function upperLeft3(m) {
    return new Float32Array([m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]]);
  }

  // ------------------------------------------------------------------ data

  function decodeBase64(text) {
    var binary = atob(text);
    var bytes = new Uint8Array(binary.length);
    for (var i = 0; i < binary.length; i++) {
      bytes[i] = binary.charCodeAt(i);
    }
    return bytes.buffer;
  }

  var data = JSON.parse(document.getElementById("face-data").textContent);
  var buffer = decodeBase64(data.buffer);
  var kinds = { float32: Float32Array, int8: Int8Array, uint16: Uint16Array, uint32: Uint32Array };

  function view(name) {
    var entry = data.layout[name];   // [type, byte offset, element count]
    return new kinds[entry[0]](buffer, entry[1], entry[2]);
  }

  // ------------------------------------------------------------------ WebGL set-up

  var gl = canvas.getContext("webgl2", { antialias: true }) || canvas.getContext("webgl", { antialias: true });
  if (!gl) {
    fail("this browser cannot draw WebGL, which the page needs");
    return;
  }
  var webgl2 = typeof WebGL2RenderingContext !== "undefined" && gl instanceof WebGL2RenderingContext;
  if (data.layout.indices[0] === "uint32" && !webgl2 && !gl.getExtension("OES_element_index_uint")) {
    fail("this browser's WebGL cannot index more than 65,536 vertices");
    return;
  }

  function compile(type, id) {
    var shader = gl.createShader(type);
    gl.shaderSource(shader, document.getElementById(id).textContent);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(id + ": " + gl.getShaderInfoLog(shader));
    }
    return shader;
  }

  var program = gl.createProgram();
  gl.attachShader(program, compile(gl.VERTEX_SHADER, "face-vert"));
  gl.attachShader(program, compile(gl.FRAGMENT_SHADER, "face-frag"));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
    fail("the shaders do not link: " + gl.getProgramInfoLog(program));
    return;
  }
  gl.useProgram(program);

  function attribute(name, array, size, type, normalized, usage) {
    var location = gl.getAttribLocation(program, name);
    var handle = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, handle);
    gl.bufferData(gl.ARRAY_BUFFER, array, usage || gl.STATIC_DRAW);
    gl.enableVertexAttribArray(location);
    gl.vertexAttribPointer(location, size, type, normalized, 0, 0);
    return handle;
  }

  attribute("aNeutral", view("neutral"), 3, gl.FLOAT, false);
  attribute("aNormalNeutral", view("normal_neutral"), 3, gl.BYTE, true);
  // A rig's page holds one field per morph target, each with its slider: the field
  // drawn is their sum weighted by the sliders (a few hundred thousand multiply-adds,
  // done here when a slider moves), and the moved normals likewise; the main slider
  // scales it all.
  var targets = data.targets || [];
  var fieldBuffer, normalBuffer, combinedField, combinedNormal;
  if (targets.length) {
    combinedField = new Float32Array(view("neutral").length);
    combinedNormal = new Float32Array(combinedField.length);
    fieldBuffer = attribute("aField", combinedField, 3, gl.FLOAT, false, gl.DYNAMIC_DRAW);
    normalBuffer = attribute("aNormalMoved", combinedNormal, 3, gl.FLOAT, false, gl.DYNAMIC_DRAW);
  } else {
    attribute("aField", view("field"), 3, gl.FLOAT, false);
    attribute("aNormalMoved", view("normal_moved"), 3, gl.BYTE, true);
  }
  attribute("aUv", view("uv"), 2, gl.UNSIGNED_SHORT, true);
  var indices = view("indices");
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer());
  gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
  var indexType = data.layout.indices[0] === "uint32" ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;

  var uniforms = {};
  ["uModelView", "uProjection", "uNormalMatrix", "uMagnitude", "uTexture", "uTextured", "uLight"]
    .forEach(function (name) { uniforms[name] = gl.getUniformLocation(program, name); });
  var light = [-0.35, 0.45, 1.0];
  var lightLength = Math.hypot(light[0], light[1], light[2]);
  gl.uniform3f(uniforms.uLight, light[0] / lightLength, light[1] / lightLength, light[2] / lightLength);
  gl.uniform1i(uniforms.uTexture, 0);
  gl.uniform1i(uniforms.uTextured, 0);
  gl.enable(gl.DEPTH_TEST);
  gl.clearColor(1, 1, 1, 1);

  // ------------------------------------------------------------------ the view

  var camera = { yaw: 0, pitch: 0, zoom: 1 };
  var fieldOfView = 30 * Math.PI / 180;
  var centre = data.centre;
  var distance = data.radius / Math.sin(fieldOfView / 2);
  var pending = false;

  function draw() {
    pending = false;
    var ratio = window.devicePixelRatio || 1;
    var width = Math.max(1, Math.round(canvas.clientWidth * ratio));
    var height = Math.max(1, Math.round(canvas.clientHeight * ratio));
    if (canvas.width !== width || canvas.height !== height) {
      canvas.width = width;
      canvas.height = height;
    }
    gl.viewport(0, 0, width, height);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    var rotation = multiply(rotationX(camera.pitch), rotationY(camera.yaw));
    var modelView = multiply(translation(0, 0, -distance * camera.zoom),
                             multiply(rotation, translation(-centre[0], -centre[1], -centre[2])));
    var far = distance * camera.zoom + 2 * data.radius;
    gl.uniformMatrix4fv(uniforms.uProjection, false,
                        perspective(fieldOfView, width / height, Math.max(1, far - 4 * data.radius), far));
    gl.uniformMatrix4fv(uniforms.uModelView, false, modelView);
    gl.uniformMatrix3fv(uniforms.uNormalMatrix, false, upperLeft3(rotation));
    gl.uniform1f(uniforms.uMagnitude, state.magnitude);
    gl.drawElements(gl.TRIANGLES, indices.length, indexType, 0);
    state.frames += 1;
  }

  function redraw() {
    if (!pending) {
      pending = true;
      window.requestAnimationFrame(draw);
    }
  }

  function setMagnitude(value) {
    state.magnitude = value;
    valueText.textContent = value.toFixed(2);
    redraw();
  }

  // ------------------------------------------------------------------ a rig's targets

  state.weights = targets.map(function () { return 0; });
  var neutralNormal = targets.length ? view("normal_neutral") : null;

  function combine() {
    var count = combinedField.length;
    for (var i = 0; i < count; i++) {
      combinedField[i] = 0;
      combinedNormal[i] = neutralNormal[i] / 127;
    }
    targets.forEach(function (name, k) {
      var weight = state.weights[k];
      if (weight === 0) {
        return;
      }
      var field = view("field_" + k), normal = view("normal_" + k);
      for (var i = 0; i < count; i++) {
        combinedField[i] += weight * field[i];
        combinedNormal[i] += weight * (normal[i] - neutralNormal[i]) / 127;
      }
    });
    gl.bindBuffer(gl.ARRAY_BUFFER, fieldBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, combinedField);
    gl.bindBuffer(gl.ARRAY_BUFFER, normalBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, combinedNormal);
    redraw();
  }

  targets.forEach(function (name, k) {
    var box = document.getElementById("targets");
    var label = document.createElement("label");
    var input = document.createElement("input");
    var output = document.createElement("output");
    input.type = "range";
    input.min = "0";
    input.max = "1";
    input.step = "0.01";
    input.value = "0";
    input.id = "target-" + k;
    label.htmlFor = input.id;
    label.textContent = name;
    output.textContent = "0.00";
    input.addEventListener("input", function () {
      state.weights[k] = parseFloat(input.value);
      output.textContent = state.weights[k].toFixed(2);
      combine();
    });
    box.appendChild(label);
    box.appendChild(input);
    box.appendChild(output);
  });
  state.setWeights = function (weights) {  // for scripts driving the page
    weights.forEach(function (value, k) {
      state.weights[k] = value;
      document.getElementById("target-" + k).value = String(value);
    });
    combine();
  };

  slider.addEventListener("input", function () {
    play.checked = false;
    setMagnitude(parseFloat(slider.value));
  });

  // play: sweep the magnitude from 0 to the slider's end and back, every 3 seconds
  var playStart = 0;
  function sweep(time) {
    if (!play.checked) {
      return;
    }
    var phase = ((time - playStart) / 3000) % 1;
    var value = parseFloat(slider.max) * (0.5 - 0.5 * Math.cos(2 * Math.PI * phase));
    slider.value = value;
    setMagnitude(value);
    window.requestAnimationFrame(sweep);
  }
  play.addEventListener("change", function () {
    if (play.checked) {
      playStart = performance.now();
      window.requestAnimationFrame(sweep);
    }
  });

  var drag = null;
  canvas.addEventListener("pointerdown", function (event) {
    drag = { x: event.clientX, y: event.clientY };
    canvas.setPointerCapture(event.pointerId);
  });
  canvas.addEventListener("pointermove", function (event) {
    if (!drag) {
      return;
    }
    camera.yaw += (event.clientX - drag.x) * 0.01;
    camera.pitch = Math.max(-1.5, Math.min(1.5, camera.pitch + (event.clientY - drag.y) * 0.01));
    drag = { x: event.clientX, y: event.clientY };
    redraw();
  });
  canvas.addEventListener("pointerup", function () { drag = null; });
  canvas.addEventListener("pointercancel", function () { drag = null; });
  canvas.addEventListener("wheel", function (event) {
    event.preventDefault();
    camera.zoom = Math.max(0.5, Math.min(3, camera.zoom * Math.exp(event.deltaY * 0.001)));
    redraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () {
    camera = { yaw: 0, pitch: 0, zoom: 1 };
    redraw();
  });
  window.addEventListener("resize", redraw);

  function start() {
    if (targets.length) {
      combine();
    }
    setMagnitude(parseFloat(slider.value));
    window.requestAnimationFrame(function () {
      state.ready = true;
    });
  }

  if (data.texture) {
    var image = new Image();
    image.onload = function () {
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, gl.createTexture());
      // a photograph's size is rarely a power of two: no mipmaps, clamped edges
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, image);
      gl.uniform1i(uniforms.uTextured, 1);
      start();
    };
    image.onerror = function () { fail("the face's photograph in the page cannot be decoded"); };
    image.src = data.texture;
  } else {
    start();
  }
})();
