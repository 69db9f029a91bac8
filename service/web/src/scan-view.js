/**
 * The 3D view of one scan: a single THREE.Points over a BufferGeometry whose positions are the
 * scan file's own floats (no copy) and whose RGBA colours are rewritten in place to recolour or
 * to hide classes (alpha 0 is discarded), so a change of colouring never rebuilds the geometry.
 * Orbit and zoom with the mouse; frames are drawn only when something changed.
 */

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

// Palette colours reach the screen as they are: no colour-space conversion anywhere.
THREE.ColorManagement.enabled = false;

const BACKGROUND = 0x101418;
const POINT_PIXELS = 2;

export class ScanView {
  constructor(container) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    this.renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(BACKGROUND, 1);
    container.append(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(60, 1, 0.1, 2000);
    this.camera.up.set(0, 0, 1); // the sensor's z points up
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener('change', () => this.requestRender());
    this.home();

    this.points = null;
    this.colors = null;
    this.pending = false;
    this.frames = 0;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  /** The camera behind and above the sensor, looking ahead. */
  home() {
    this.camera.position.set(-28, -14, 26);
    this.controls.target.set(8, 0, 0);
    this.controls.update();
  }

  resize() {
    const { clientWidth: width, clientHeight: height } = this.container;
    if (!width || !height) return;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  /**
   * Show a scan: `records` holds `stride` float32 values per point, x, y, z first. Returns the
   * RGBA array (4 bytes per point) to fill before calling `colorsChanged`.
   */
  show(records, stride) {
    if (this.points) {
      this.scene.remove(this.points);
      this.points.geometry.dispose();
      this.points.material.dispose();
    }
    const count = records.length / stride;
    const geometry = new THREE.BufferGeometry();
    const buffer = new THREE.InterleavedBuffer(records, stride);
    geometry.setAttribute('position', new THREE.InterleavedBufferAttribute(buffer, 3, 0));
    this.colors = new Uint8Array(count * 4);
    const color = new THREE.BufferAttribute(this.colors, 4, true);
    color.setUsage(THREE.DynamicDrawUsage);
    geometry.setAttribute('color', color);
    geometry.computeBoundingSphere();
    const material = new THREE.PointsMaterial({
      size: POINT_PIXELS,
      sizeAttenuation: false,
      vertexColors: true,
      alphaTest: 0.5,
    });
    this.points = new THREE.Points(geometry, material);
    this.scene.add(this.points);
    this.home();
    return this.colors;
  }

  /** Upload the rewritten colours and draw. */
  colorsChanged() {
    if (!this.points) return;
    this.points.geometry.getAttribute('color').needsUpdate = true;
    this.requestRender();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
    this.frames += 1;
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.render();
    });
  }

  /** Resolves once a frame with the current points has been drawn and presented. */
  drawn() {
    this.render();
    return new Promise((resolve) => requestAnimationFrame(() => resolve()));
  }

  /** Orbit the camera a full turn over `frames` frames; the median milliseconds per frame. */
  async orbitFrames(frames = 60) {
    const times = [];
    const angle = (2 * Math.PI) / frames;
    const offset = this.camera.position.clone().sub(this.controls.target);
    const turn = new THREE.Quaternion().setFromAxisAngle(this.camera.up, angle);
    let last = performance.now();
    for (let i = 0; i < frames; i++) {
      offset.applyQuaternion(turn);
      this.camera.position.copy(this.controls.target).add(offset);
      this.camera.lookAt(this.controls.target);
      this.render();
      await new Promise((resolve) => requestAnimationFrame(resolve));
      const now = performance.now();
      times.push(now - last);
      last = now;
    }
    this.home();
    this.requestRender();
    times.sort((a, b) => a - b);
    return times[Math.floor(times.length / 2)];
  }

  /** The current picture as a PNG Blob. */
  image() {
    this.render();
    return new Promise((resolve) => this.renderer.domElement.toBlob(resolve, 'image/png'));
  }
}
