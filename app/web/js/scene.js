// The 3D view of a map (three.js): each card as its square with its id, the disc
// centres, colour by the card's survey standard deviation, the survey's camera
// trajectory, and a live camera with its position uncertainty.

import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

/** Standard deviations (m) at the two ends of the colour scale, on a log scale. */
export const STD_SCALE_M = [1e-4, 1e-2];

/** Colour of a standard deviation: green (precise) through yellow to red (poor). */
export function stdColour(stdM) {
  const [lo, hi] = STD_SCALE_M.map(Math.log10);
  const x = Math.min(1, Math.max(0, (Math.log10(Math.max(stdM, 1e-9)) - lo) / (hi - lo)));
  return new THREE.Color().setHSL((1 - x) * 0.33, 0.75, 0.5);
}

/**
 * The affine map from card units (u, v in 0..1) to 3D fitted to the four disc centres
 * (least squares): returns the card's four corners in 3D.
 */
export function cardCorners(discs3d, discsUv) {
  // X = O + u A + v B: solve the 3x3 normal equations of [1 u v] for each coordinate.
  const M = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  const rhs = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  discsUv.forEach(([u, v], i) => {
    const row = [1, u, v];
    for (let a = 0; a < 3; a++) {
      for (let b = 0; b < 3; b++) M[a][b] += row[a] * row[b];
      for (let c = 0; c < 3; c++) rhs[a][c] += row[a] * discs3d[i][c];
    }
  });
  const inv = new THREE.Matrix3().set(...M.flat()).invert();
  const e = inv.elements;  // column-major
  const coef = [0, 1, 2].map((r) => [0, 1, 2].map((c) => e[r] * rhs[0][c] + e[r + 3] * rhs[1][c] + e[r + 6] * rhs[2][c]));
  const at = (u, v) => new THREE.Vector3(...[0, 1, 2].map((c) => coef[0][c] + u * coef[1][c] + v * coef[2][c]));
  return [at(0, 0), at(1, 0), at(1, 1), at(0, 1)];
}

/** Eigen-decomposition of a symmetric 3x3 matrix (Jacobi): [values, vectors as columns]. */
export function symmetricEigen(matrix) {
  const a = matrix.map((row) => [...row]);
  const v = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  for (let sweep = 0; sweep < 30; sweep++) {
    for (const [p, q] of [[0, 1], [0, 2], [1, 2]]) {
      if (Math.abs(a[p][q]) < 1e-30) continue;
      const theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
      const t = Math.sign(theta || 1) / (Math.abs(theta) + Math.sqrt(theta * theta + 1));
      const c = 1 / Math.sqrt(t * t + 1);
      const s = t * c;
      for (let k = 0; k < 3; k++) {
        const akp = a[k][p], akq = a[k][q];
        a[k][p] = c * akp - s * akq; a[k][q] = s * akp + c * akq;
      }
      for (let k = 0; k < 3; k++) {
        const apk = a[p][k], aqk = a[q][k];
        a[p][k] = c * apk - s * aqk; a[q][k] = s * apk + c * aqk;
      }
      for (let k = 0; k < 3; k++) {
        const vkp = v[k][p], vkq = v[k][q];
        v[k][p] = c * vkp - s * vkq; v[k][q] = s * vkp + c * vkq;
      }
    }
  }
  return [[a[0][0], a[1][1], a[2][2]], v];
}

function label(text, heightM) {
  const canvas = document.createElement("canvas");
  canvas.width = 128; canvas.height = 64;
  const g = canvas.getContext("2d");
  g.fillStyle = "rgba(16,21,27,0.75)"; g.fillRect(0, 0, 128, 64);
  g.fillStyle = "#fff"; g.font = "bold 40px sans-serif"; g.textAlign = "center"; g.textBaseline = "middle";
  g.fillText(text, 64, 34);
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(canvas), depthTest: false }));
  sprite.scale.set(heightM * 2, heightM, 1);
  return sprite;
}

/** Empty a group, freeing its objects' GPU buffers and textures (the live camera is redrawn per frame). */
function clearGroup(group) {
  group.traverse((object) => {
    object.geometry?.dispose();
    for (const material of [object.material].flat()) {
      material?.map?.dispose();
      material?.dispose();
    }
  });
  group.clear();
}

/** The map frame's up direction: z in a world frame (alignment puts the floor at z = 0), -y in the survey's. */
function upOf(map) {
  return map.frame === "world" ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(0, -1, 0);
}

export class MapView {
  /** A view in `container`, drawn at most `maxFps` times a second. */
  constructor(container, { maxFps = 60 } = {}) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
    container.append(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x10151b);
    this.camera = new THREE.PerspectiveCamera(55, 1, 0.01, 500);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.mapGroup = new THREE.Group();
    this.trajectoryGroup = new THREE.Group();
    this.liveGroup = new THREE.Group();
    this.scene.add(this.mapGroup, this.trajectoryGroup, this.liveGroup);
    this.cards = new Map();  // id -> {mesh, centre, std}
    this.size = 1;
    this.centre = new THREE.Vector3();
    this.up = new THREE.Vector3(0, 0, 1);
    this.resize = () => {
      const width = container.clientWidth || 640, height = container.clientHeight || 480;
      this.renderer.setSize(width, height);
      this.camera.aspect = width / height;
      this.camera.updateProjectionMatrix();
      this.requestRender();
    };
    this.observer = new ResizeObserver(this.resize);
    this.running = true;
    this.frameQueued = false;
    this.lastFrame = -Infinity;
    this.livePose = null;  // the live camera's newest pose, and whether it is drawn yet
    this.liveChanged = false;
    this.minFrameMs = 1000 / maxFps;
    this.frames = 0;  // frames drawn: the view draws only when something changed
    this.controls.addEventListener("change", () => this.requestRender());
    this.observer.observe(container);
    this.resize();
  }

  /**
   * Draw the view once, at the next animation frame, at most `maxFps` times a second.
   * Nothing is drawn while nothing changes: a browser without a GPU draws in software,
   * and a view redrawn 60 times a second takes a core from the page's own work.
   */
  requestRender() {
    if (this.frameQueued || !this.running) return;
    this.frameQueued = true;
    const wait = Math.max(0, this.lastFrame + this.minFrameMs - performance.now());
    setTimeout(() => requestAnimationFrame(() => {
      this.frameQueued = false;
      if (!this.running) return;
      this.lastFrame = performance.now();
      if (this.liveChanged) {
        this.buildCamera(this.livePose);
        this.liveChanged = false;
      }
      const moving = this.controls.update();  // damping: the view glides on after a drag
      this.renderer.render(this.scene, this.camera);
      this.frames += 1;
      if (moving) this.requestRender();
    }), wait);
  }

  /** Draw a map document; `discsUv` are the card layout's disc centres in card units. */
  setMap(map, discsUv) {
    clearGroup(this.mapGroup);
    this.cards.clear();
    this.up = upOf(map);
    const box = new THREE.Box3();
    const discPoints = [];
    for (const target of map.targets) {
      const corners = cardCorners(target.discs, discsUv);
      const std = target.std_m ? Math.max(...target.std_m) : NaN;  // a map written by hand may have none
      const geometry = new THREE.BufferGeometry().setFromPoints([corners[0], corners[1], corners[2], corners[0],
                                                                  corners[2], corners[3]]);
      geometry.computeVertexNormals();
      const mesh = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({
        color: Number.isFinite(std) ? stdColour(std) : new THREE.Color(0x9aa7b4), side: THREE.DoubleSide,
        transparent: true, opacity: 0.85 }));
      mesh.userData = { id: target.id };
      const outline = new THREE.LineLoop(new THREE.BufferGeometry().setFromPoints(corners),
                                         new THREE.LineBasicMaterial({ color: 0xffffff }));
      const centre = corners.reduce((s, c) => s.add(c), new THREE.Vector3()).multiplyScalar(0.25);
      const side = corners[0].distanceTo(corners[1]);
      const tag = label(String(target.id), side * 0.5);
      tag.position.copy(centre).addScaledVector(this.up, side * 0.6);
      this.mapGroup.add(mesh, outline, tag);
      this.cards.set(target.id, { mesh, outline, centre, std, side });
      for (const disc of target.discs) { discPoints.push(new THREE.Vector3(...disc)); box.expandByPoint(discPoints.at(-1)); }
    }
    this.mapGroup.add(new THREE.Points(new THREE.BufferGeometry().setFromPoints(discPoints),
                                       new THREE.PointsMaterial({ color: 0x111111, size: 4, sizeAttenuation: false })));
    if (!box.isEmpty()) {
      box.getCenter(this.centre);
      this.size = Math.max(0.5, box.getSize(new THREE.Vector3()).length());
    }
    const grid = new THREE.GridHelper(Math.ceil(this.size * 1.5), Math.ceil(this.size * 1.5), 0x3a4652, 0x232c35);
    grid.quaternion.setFromUnitVectors(new THREE.Vector3(0, 1, 0), this.up);
    // The floor of a world frame (z = 0) under the map.
    grid.position.copy(this.centre).addScaledVector(this.up, -this.up.dot(this.centre));
    if (map.frame === "world") this.mapGroup.add(grid);
    this.mapGroup.add(new THREE.AxesHelper(Math.max(0.2, this.size * 0.08)));
    this.camera.up.copy(this.up);
    this.perspective();
  }

  /** The survey's camera trajectory: the registered frames' camera centres, in order. */
  setTrajectory(positions) {
    clearGroup(this.trajectoryGroup);
    this.requestRender();
    if (positions.length < 2) return;
    const points = positions.map((p) => new THREE.Vector3(...p));
    this.trajectoryGroup.add(
      new THREE.Line(new THREE.BufferGeometry().setFromPoints(points), new THREE.LineBasicMaterial({ color: 0x64b5f6 })),
      new THREE.Points(new THREE.BufferGeometry().setFromPoints(points),
                       new THREE.PointsMaterial({ color: 0x90caf9, size: 3, sizeAttenuation: false })));
  }

  /**
   * The live camera: a frustum at the pose (R, t map->camera, OpenCV axes) and its
   * position's 3-sigma ellipsoid from the covariance (m^2). null hides it. Built when the
   * view is next drawn, so that poses arriving faster than it draws cost nothing.
   */
  setCamera(pose) {
    this.livePose = pose;
    this.liveChanged = true;
    this.requestRender();
  }

  buildCamera(pose) {
    clearGroup(this.liveGroup);
    if (!pose) return;
    const R = pose.R;
    const C = new THREE.Vector3(...pose.position);
    const s = Math.max(0.15, this.size * 0.04);
    const toMap = (x, y, z) => new THREE.Vector3(  // R^T [x y z] + C
      R[0][0] * x + R[1][0] * y + R[2][0] * z, R[0][1] * x + R[1][1] * y + R[2][1] * z,
      R[0][2] * x + R[1][2] * y + R[2][2] * z).add(C);
    const corners = [[-0.6, -0.45], [0.6, -0.45], [0.6, 0.45], [-0.6, 0.45]].map(([x, y]) => toMap(x * s, y * s, s));
    const segments = [];
    corners.forEach((corner, i) => segments.push(C, corner, corner, corners[(i + 1) % 4]));
    segments.push(corners[0], toMap(0, -0.7 * s, s), toMap(0, -0.7 * s, s), corners[1]);  // "up" notch
    this.liveGroup.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(segments),
                                              new THREE.LineBasicMaterial({ color: 0xffb300 })));
    const cov = pose.covariance_position;
    if (cov) {
      const [values, vectors] = symmetricEigen(cov);
      const ellipsoid = new THREE.Mesh(new THREE.SphereGeometry(1, 16, 12),
        new THREE.MeshBasicMaterial({ color: 0xffb300, transparent: true, opacity: 0.35 }));
      const basis = new THREE.Matrix4().makeBasis(
        ...[0, 1, 2].map((k) => new THREE.Vector3(vectors[0][k], vectors[1][k], vectors[2][k])));
      ellipsoid.applyMatrix4(new THREE.Matrix4().makeScale(...values.map((v) => 3 * Math.sqrt(Math.max(v, 0)))));
      ellipsoid.applyMatrix4(basis);
      ellipsoid.position.copy(C);
      this.liveGroup.add(ellipsoid);
    }
  }

  /** Highlight one card and look at it. */
  focusCard(id) {
    for (const [cardId, card] of this.cards) card.outline.material.color.set(cardId === id ? 0x00e5ff : 0xffffff);
    const card = this.cards.get(id);
    if (!card) return false;
    this.controls.target.copy(card.centre);
    this.camera.position.copy(card.centre).addScaledVector(this.up, card.side * 4)
      .add(new THREE.Vector3(card.side * 3, card.side * 3, card.side * 3).projectOnPlane(this.up));
    this.requestRender();
    return true;
  }

  /** Look straight down on the map along its up direction. */
  topDown() {
    this.controls.target.copy(this.centre);
    const side = new THREE.Vector3(1, 0, 0).projectOnPlane(this.up).normalize().multiplyScalar(1e-3 * this.size);
    this.camera.position.copy(this.centre).addScaledVector(this.up, this.size * 1.1).add(side);
    this.requestRender();
  }

  /** An oblique view of the whole map. */
  perspective() {
    this.controls.target.copy(this.centre);
    const across = new THREE.Vector3(1, 0.6, 0.3).projectOnPlane(this.up).normalize();
    this.camera.position.copy(this.centre).addScaledVector(across, this.size * 0.9).addScaledVector(this.up, this.size * 0.6);
    this.requestRender();
  }

  dispose() {
    this.running = false;
    for (const group of [this.mapGroup, this.trajectoryGroup, this.liveGroup]) clearGroup(group);
    this.observer.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
  }
}
