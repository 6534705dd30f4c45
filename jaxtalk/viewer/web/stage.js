// What both pages of `jaxtalk view` draw in: a renderer filling `container`, lights, and `object` (the loaded
// glTF scene) in front of a camera framed on its neutral pose once (a per-frame fit would zoom with the
// jaw), with orbit controls and resizing. The face looks down +z.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

export function stage(container, object) {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(window.innerWidth, window.innerHeight);
  container.appendChild(renderer.domElement);

  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x202428);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 1.6));
  const key = new THREE.DirectionalLight(0xffffff, 2.0);
  key.position.set(0.4, 0.6, 1.0);
  scene.add(key);
  scene.add(object);

  const box = new THREE.Box3().setFromObject(object);
  const centre = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const camera = new THREE.PerspectiveCamera(30, window.innerWidth / window.innerHeight, 0.01, 100);
  const distance = 1.3 * Math.max(size.x, size.y) / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
  camera.position.set(centre.x, centre.y, box.max.z + distance);
  camera.lookAt(centre);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.copy(centre);

  window.addEventListener("resize", () => {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
  });
  const draw = () => { controls.update(); renderer.render(scene, camera); };
  return { renderer, scene, camera, controls, draw };
}
