// CCMD live map view (docs/view.md). Reads the server's state once, then follows its event
// stream: keyframes, their clouds, pose updates, loops and fusions, per-agent statistics.
//
// Drawing: a keyframe's points stay in its camera frame on the GPU; its pose is one 3x4
// matrix in a uniform array, so a pose update moves all its points by changing 12 numbers
// (the paper's update strategy carried to the screen). Points are grouped per agent in
// chunks of up to SLOTS keyframes (one uniform array each) and, inside a chunk, in levels of
// detail: the server sends every cloud in a shuffled order, so the first 1/256 of it is an
// even subsample, the next 1/256 another, then 1/128, 1/64, ... 1/2. While the camera
// moves, the view draws the coarsest levels that fit a point budget that adapts to hold
// 30 frames per second; when it stops, the remaining levels are added frame by frame on top
// of the same image until every point is drawn. A released cloud is hidden at once and leaves
// the buffers when its chunk is compacted (see Chunk): they follow the clouds drawn, not the
// clouds ever loaded.
(function () {
  'use strict';

  const SLOTS = 256;
  const LEVEL_ENDS = [1 / 256, 2 / 256, 4 / 256, 8 / 256, 16 / 256, 32 / 256, 64 / 256, 128 / 256, 1];
  const TARGET_MS = 1000 / 30;
  const MIN_BUDGET = 10000;
  const REFINE_AFTER_MS = 250;
  const COLOURS = ['#1e50c8', '#f08c28', '#3caa3c', '#d23232', '#965aaa', '#c8be28', '#787878', '#149696'];
  const token = new URLSearchParams(location.search).get('token');

  function apiUrl(path, params) {
    const p = new URLSearchParams(params || {});
    if (token) p.set('token', token);
    const q = p.toString();
    return q ? path + '?' + q : path;
  }
  // Agents are coloured in the order of their names (agent1, agent2, ... agent10), as in the
  // replay report's plots; ids follow the order agents first connected.
  let agentOrder = [];
  function agentColour(a) {
    const i = agentOrder.indexOf(a);
    return COLOURS[(i >= 0 ? i : agentOrder.length + a) % COLOURS.length];
  }
  function sortAgents(names) {
    return [...names.keys()].sort((p, q) =>
      names.get(p).localeCompare(names.get(q), 'en', { numeric: true }) || p - q);
  }
  function key(a, k) { return a + ':' + k; }
  // The server stamps events with its wall clock; on the same machine the browser's agrees.
  function nowMs() { return Date.now(); }

  // ------------------------------------------------------------------ state

  const S = {
    seq: 0,                 // last event applied
    agents: new Map(),      // id -> name
    keyframes: new Map(),   // "a:k" -> keyframe
    loops: [],
    stats: null,
    statsVersion: 0,
    connection: 'connecting',
    frames: 0,
    latency: { keyframe: [], backend: [], cloud: [], pose: [], delivery: [], fetch: [], frame: [], server: [] },
    pendingPose: [],        // pose events applied but not yet drawn: {t, src}
    cloudErrors: 0,
  };

  function newKeyframe(a, k) {
    return { a: a, k: k, m: 0, T: new Float64Array(12), cloud: false, loaded: false, drawn: false,
      moves: 0, arrived: 0, ready: 0, chunk: null, slot: -1, points: 0, fetching: false };
  }

  function setPose(kf, T, offset) {
    for (let i = 0; i < 12; ++i) kf.T[i] = T[offset + i];
    if (kf.chunk) kf.chunk.setPose(kf.slot, kf.T);
  }

  let frameRequested = false;  // a frame is scheduled (frames are drawn on demand, see frame())

  // How the map is drawn: level of detail (see the top of this file) and display options.
  const view = {
    fresh: true,          // the next frame starts a new image
    refine: [],           // slices still to draw on the current image: [level, first, count]
    budget: 400000,       // points per fresh frame
    totalPoints: 0,       // points of the drawn clouds
    loadedPoints: 0,      // points loaded since the page last loaded the server's state (released ones too)
    drawnLevels: 0,
    drawnPoints: 0,
    byAgent: false,
    pointSize: 2,
    showOverlay: true,
    lastFrame: 0,
    lastRendered: false,
    changedAt: 0,         // when the last fresh image started
    follow: 0,
    userMoved: false,     // the camera is the user's: no more automatic framing
  };

  // ------------------------------------------------------------------ scene

  const container = document.getElementById('scene');
  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.autoClear = false;
  renderer.setClearColor(0x15181d);
  container.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(60, 1, 0.02, 500);
  camera.up.set(0, -1, 0);  // the map frame is the first camera's: y points down
  camera.position.set(0, -2.5, -3.5);
  const controls = new THREE.OrbitControls(camera, renderer.domElement);
  controls.target.set(0, 0, 1.5);
  controls.update();
  controls.addEventListener('change', function () { markFresh(); });

  const overlay = new THREE.Group();  // trajectories and loop edges
  scene.add(overlay);

  const vertexShader = [
    'precision highp float;',
    'uniform mat4 modelViewMatrix;',
    'uniform mat4 projectionMatrix;',
    'uniform vec4 poses[' + (3 * SLOTS) + '];',
    'uniform vec3 agentColour;',
    'uniform float byAgent;',
    'uniform float pointSize;',
    'attribute vec3 position;',
    'attribute vec3 color;',
    'attribute float slot;',
    'varying vec3 vColour;',
    'void main() {',
    '  int i = int(slot) * 3;',
    '  if (poses[i] == vec4(0.0)) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); return; }',  // released
    '  vec4 p = vec4(position, 1.0);',
    '  vec4 w = vec4(dot(poses[i], p), dot(poses[i + 1], p), dot(poses[i + 2], p), 1.0);',
    '  gl_Position = projectionMatrix * (modelViewMatrix * w);',
    '  gl_PointSize = pointSize;',
    '  vColour = mix(color, agentColour, byAgent);',
    '}'].join('\n');
  const fragmentShader = [
    'precision mediump float;',
    'varying vec3 vColour;',
    'void main() { gl_FragColor = vec4(vColour, 1.0); }'].join('\n');

  // One level of one chunk: a growing buffer drawn with one call.
  function Level(chunk) {
    this.chunk = chunk;
    this.capacity = 0;
    this.count = 0;
    this.points = null;
  }
  Level.prototype.reserve = function (n) {
    if (this.count + n <= this.capacity) return;
    this.rebuild(Math.max(4096, this.capacity * 2, this.count + n), null);
  };
  // New arrays of `capacity` points with this level's points, in their order, but those of the
  // slots flagged in `drop` (null: all of them). The old arrays leave the GPU and the page.
  Level.prototype.rebuild = function (capacity, drop) {
    const pos = new Int16Array(capacity * 3), col = new Uint8Array(capacity * 3), slot = new Uint16Array(capacity);
    let count = 0;
    if (this.points) {
      const g = this.points.geometry;
      const oldPos = g.attributes.position.array, oldCol = g.attributes.color.array, oldSlot = g.attributes.slot.array;
      // A keyframe's points are one run in a level: copy runs of kept points at once.
      for (let i = 0; i < this.count;) {
        let j = i;
        while (j < this.count && !(drop && drop[oldSlot[j]])) ++j;
        if (j > i) {
          pos.set(oldPos.subarray(i * 3, j * 3), count * 3);
          col.set(oldCol.subarray(i * 3, j * 3), count * 3);
          slot.set(oldSlot.subarray(i, j), count);
          count += j - i;
        }
        i = j;
        while (i < this.count && drop && drop[oldSlot[i]]) ++i;
      }
      this.chunk.group.remove(this.points);
      g.dispose();
    }
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    g.setAttribute('color', new THREE.BufferAttribute(col, 3, true));
    g.setAttribute('slot', new THREE.BufferAttribute(slot, 1));
    g.setDrawRange(0, count);
    this.points = new THREE.Points(g, this.chunk.material);
    this.points.frustumCulled = false;
    this.points.matrixAutoUpdate = false;
    this.chunk.group.add(this.points);
    this.capacity = capacity;
    this.count = count;
  };
  Level.prototype.append = function (positions, colours, first, last, slotIndex) {
    const n = last - first;
    if (n <= 0) return;
    this.reserve(n);
    const g = this.points.geometry;
    const at = this.count;
    g.attributes.position.array.set(positions.subarray(first * 3, last * 3), at * 3);
    g.attributes.color.array.set(colours.subarray(first * 3, last * 3), at * 3);
    g.attributes.slot.array.fill(slotIndex, at, at + n);
    for (const [name, size] of [['position', 3], ['color', 3], ['slot', 1]]) {
      // Upload only what is new; three.js resets the range to -1 after each upload, and
      // several keyframes arriving before a frame widen it.
      const r = g.attributes[name].updateRange;
      const end = (at + n) * size;
      const start = r.count < 0 ? at * size : Math.min(r.offset, at * size);
      r.count = Math.max(end, r.count < 0 ? 0 : r.offset + r.count) - start;
      r.offset = start;
      g.attributes[name].needsUpdate = true;
    }
    this.count += n;
    g.setDrawRange(0, this.count);
  };

  // Drops the points of the slots flagged in `drop`; the level keeps room for half as many
  // again, and an emptied level frees its buffer.
  Level.prototype.compact = function (drop) {
    if (!this.points) return;
    const slots = this.points.geometry.attributes.slot.array;
    let kept = 0;
    for (let i = 0; i < this.count; ++i) kept += drop[slots[i]] ? 0 : 1;
    if (kept === this.count) return;
    if (kept > 0) {
      this.rebuild(Math.max(4096, Math.ceil(kept * 1.5)), drop);
      return;
    }
    this.chunk.group.remove(this.points);
    this.points.geometry.dispose();
    this.points = null;
    this.capacity = this.count = 0;
  };

  // Up to SLOTS keyframes of one agent. A released keyframe's slot is first hidden (its points
  // stay in the levels, clipped); once the hidden points are more than half of the chunk's,
  // the levels are rebuilt without them and the slots are free for new clouds. The slots of
  // drawn keyframes and their poses stay as they are: nothing on screen changes.
  function Chunk(agent) {
    this.agent = agent;
    this.used = 0;                         // slots handed out so far
    this.free = [];                        // slots with no point left in the levels
    this.live = 0;                         // slots whose cloud is drawn
    this.hidden = 0;                       // points of released slots still in the levels
    this.released = new Uint8Array(SLOTS);  // 1: released, its points still in the levels
    this.rows = [];
    for (let i = 0; i < 3 * SLOTS; ++i) this.rows.push(new THREE.Vector4(0, 0, 0, 0));
    this.material = new THREE.RawShaderMaterial({
      vertexShader: vertexShader, fragmentShader: fragmentShader,
      uniforms: {
        poses: { value: this.rows },
        agentColour: { value: new THREE.Color(agentColour(agent)) },
        byAgent: { value: view.byAgent ? 1 : 0 },
        pointSize: { value: view.pointSize },
      },
    });
    this.group = new THREE.Group();
    scene.add(this.group);
    this.levels = LEVEL_ENDS.map(() => new Level(this));
  }
  Chunk.prototype.hasRoom = function () { return this.free.length > 0 || this.used < SLOTS; };
  Chunk.prototype.take = function () {
    this.live++;
    return this.free.length ? this.free.pop() : this.used++;
  };
  // Points held in the levels, drawn or not.
  Chunk.prototype.stored = function () {
    let n = 0;
    for (const level of this.levels) n += level.count;
    return n;
  };
  Chunk.prototype.setPose = function (slot, T) {
    for (let r = 0; r < 3; ++r) {
      // Points are in millimetres: the scale goes into the rotation part.
      this.rows[3 * slot + r].set(T[4 * r] * 1e-3, T[4 * r + 1] * 1e-3, T[4 * r + 2] * 1e-3, T[4 * r + 3]);
    }
  };
  // A released cloud of n points: its slot's pose is zero, which the vertex shader clips, until
  // the levels are compacted.
  Chunk.prototype.release = function (slot, n) {
    for (let r = 0; r < 3; ++r) this.rows[3 * slot + r].set(0, 0, 0, 0);
    this.live--;
    if (n > 0) {
      this.released[slot] = 1;
      this.hidden += n;
    } else {
      this.free.push(slot);  // nothing of it in the levels
    }
  };
  // Rebuilds the levels without the released slots' points; those slots become free.
  Chunk.prototype.compact = function () {
    for (const level of this.levels) level.compact(this.released);
    for (let slot = 0; slot < this.used; ++slot) {
      if (this.released[slot]) this.free.push(slot);
    }
    this.released.fill(0);
    this.hidden = 0;
  };
  Chunk.prototype.dispose = function () {
    for (const level of this.levels) if (level.points) level.points.geometry.dispose();
    this.material.dispose();
    scene.remove(this.group);
  };

  const chunks = [];
  const openChunk = new Map();  // agent -> the chunk its last cloud went to

  // A chunk of the agent with a free slot: the last one used, else any, else a new one.
  function chunkFor(a) {
    let chunk = openChunk.get(a);
    if (!chunk || !chunk.hasRoom()) chunk = chunks.find((c) => c.agent === a && c.hasRoom());
    if (!chunk) {
      chunk = new Chunk(a);
      chunks.push(chunk);
    }
    openChunk.set(a, chunk);
    return chunk;
  }

  function addCloud(kf, positions, colours, n) {
    const chunk = chunkFor(kf.a);
    kf.chunk = chunk;
    kf.slot = chunk.take();
    kf.points = n;
    chunk.setPose(kf.slot, kf.T);
    let first = 0;
    LEVEL_ENDS.forEach(function (end, l) {
      const last = l === LEVEL_ENDS.length - 1 ? n : Math.min(n, Math.ceil(n * end));
      chunk.levels[l].append(positions, colours, first, last, kf.slot);
      first = Math.max(first, last);
    });
    kf.loaded = true;
    kf.fetched = nowMs();
    if (kf.told) S.latency.fetch.push(kf.fetched - kf.told);
    view.totalPoints += n;
    view.loadedPoints += n;
    markFresh();
  }

  // The dense store released the keyframe's cloud (or the keyframe left the dense map): nothing
  // of it is drawn any more, and its points leave the page with the next compaction of its
  // chunk (a chunk left with no cloud at once). A cloud loaded again later (the keyframe back
  // in the dense map) takes a new slot: the old copy goes with the compaction.
  function dropCloud(kf) {
    const chunk = kf.chunk;
    if (chunk) {
      chunk.release(kf.slot, kf.points);
      if (chunk.live === 0) {
        chunk.dispose();
        chunks.splice(chunks.indexOf(chunk), 1);
        if (openChunk.get(chunk.agent) === chunk) openChunk.delete(chunk.agent);
      } else if (2 * chunk.hidden > chunk.stored()) {
        chunk.compact();
      }
    }
    kf.chunk = null;
    kf.slot = -1;
    view.totalPoints -= kf.points;
    kf.points = 0;
    kf.loaded = kf.cloud = kf.drawn = false;
    markFresh();
  }

  function clearScene() {
    for (const c of chunks) c.dispose();
    chunks.length = 0;
    openChunk.clear();
    view.totalPoints = 0;
    view.loadedPoints = 0;
  }

  // ------------------------------------------------------------------ level of detail


  function levelPoints(l) {
    let n = 0;
    for (const c of chunks) n += c.levels[l].count;
    return n;
  }

  // The coarsest levels whose points fit the budget (at least the first).
  function levelsForBudget() {
    let n = 0, levels = 0;
    for (let l = 0; l < LEVEL_ENDS.length; ++l) {
      const add = levelPoints(l);
      if (levels > 0 && n + add > view.budget) break;
      n += add;
      levels = l + 1;
    }
    return { levels: levels, points: n };
  }

  function setVisibleLevels(from, to) {
    for (const c of chunks) {
      c.levels.forEach(function (level, l) {
        if (!level.points) return;
        level.points.visible = l >= from && l < to;
        level.points.geometry.setDrawRange(0, level.count);
      });
    }
  }

  function drawFresh() {
    view.changedAt = performance.now();
    const choice = levelsForBudget();
    setVisibleLevels(0, choice.levels);
    overlay.visible = view.showOverlay;
    renderer.clear();
    renderer.render(scene, camera);
    view.drawnLevels = choice.levels;
    view.drawnPoints = choice.points;
    // What is left for the still camera: the finer levels, in slices of about the budget.
    view.refine = [];
    for (let l = choice.levels; l < LEVEL_ENDS.length; ++l) {
      for (const c of chunks) {
        const level = c.levels[l];
        for (let first = 0; first < level.count; first += view.budget) {
          view.refine.push([level, first, Math.min(view.budget, level.count - first)]);
        }
      }
    }
  }

  function drawRefinement() {
    let drawn = 0;
    for (const c of chunks) for (const level of c.levels) if (level.points) level.points.visible = false;
    overlay.visible = false;
    const shown = [];
    while (view.refine.length && drawn < view.budget) {
      const [level, first, count] = view.refine.shift();
      level.points.visible = true;
      level.points.geometry.setDrawRange(first, count);
      shown.push(level);
      drawn += count;
      // Slices of the same level in one frame need separate draws: draw now.
      renderer.render(scene, camera);
      level.points.visible = false;
    }
    for (const level of shown) level.points.geometry.setDrawRange(0, level.count);
    view.drawnPoints += drawn;
  }

  function adaptBudget(frameMs) {
    if (frameMs > TARGET_MS * 1.1) {
      view.budget = Math.max(MIN_BUDGET, Math.round(view.budget * Math.max(0.5, TARGET_MS / frameMs)));
    } else if (frameMs < TARGET_MS * 0.7 && view.budget < view.totalPoints) {
      view.budget = Math.round(view.budget * 1.15);
    }
  }

  // ------------------------------------------------------------------ overlay: trajectories, loops

  let overlayDirty = true;
  function markOverlay() { overlayDirty = true; requestDraw(); }

  function primaryMap() {
    if (S.stats && S.stats.map_list) {
      for (const m of S.stats.map_list) if (m.primary) return m.id;
    }
    let best = null;
    for (const kf of S.keyframes.values()) if (kf.cloud && (best === null || kf.a < best.a)) best = kf;
    if (best) return best.m;
    for (const kf of S.keyframes.values()) if (best === null || kf.a < best.a) best = kf;
    return best ? best.m : 0;
  }

  // Maps not fused with the world map are drawn beside it, one after the other along x.
  function mapOffsets() {
    const primary = primaryMap();
    let maxX = 0, minX = 0;
    const extents = new Map();
    for (const kf of S.keyframes.values()) {
      const x = kf.T[3];
      const e = extents.get(kf.m) || [Infinity, -Infinity];
      extents.set(kf.m, [Math.min(e[0], x), Math.max(e[1], x)]);
    }
    const offsets = new Map([[primary, 0]]);
    if (extents.has(primary)) { minX = extents.get(primary)[0]; maxX = extents.get(primary)[1]; }
    let next = maxX + 2;
    for (const [m, e] of [...extents.entries()].sort((p, q) => p[0] - q[0])) {
      if (m === primary) continue;
      offsets.set(m, next - e[0]);
      next += e[1] - e[0] + 2;
    }
    return offsets;
  }

  function rebuildOverlay() {
    overlayDirty = false;
    while (overlay.children.length) {
      const o = overlay.children.pop();
      o.geometry.dispose();
      o.material.dispose();
    }
    const offsets = mapOffsets();
    const perAgent = new Map();
    for (const kf of S.keyframes.values()) {
      if (!perAgent.has(kf.a)) perAgent.set(kf.a, []);
      perAgent.get(kf.a).push(kf);
    }
    const centre = (kf) => [kf.T[3] + (offsets.get(kf.m) || 0), kf.T[7], kf.T[11]];
    for (const [a, list] of perAgent) {
      list.sort((p, q) => p.k - q.k);
      // A trajectory is cut where its keyframes change map (before a fusion).
      let run = [];
      const flush = function () {
        if (run.length > 1) {
          const g = new THREE.BufferGeometry();
          g.setAttribute('position', new THREE.Float32BufferAttribute(run.flat(), 3));
          overlay.add(new THREE.Line(g, new THREE.LineBasicMaterial({ color: agentColour(a) })));
        }
        if (run.length) {
          const g = new THREE.BufferGeometry();
          g.setAttribute('position', new THREE.Float32BufferAttribute(run.flat(), 3));
          overlay.add(new THREE.Points(g, new THREE.PointsMaterial({ color: agentColour(a), size: 5, sizeAttenuation: false })));
        }
        run = [];
      };
      let map = null;
      for (const kf of list) {
        if (kf.culled) continue;  // redundant: the server keeps it only for its cloud
        if (kf.unplaced) { flush(); map = null; continue; }  // not drawn until a loop places it
        if (map !== null && kf.m !== map) flush();
        map = kf.m;
        run.push(centre(kf));
      }
      flush();
    }
    const loops = [], fusions = [];
    for (const l of S.loops) {
      const q = S.keyframes.get(key(l.qa, l.qk)), c = S.keyframes.get(key(l.ca, l.ck));
      if (!q || !c || q.m !== c.m) continue;
      (l.fusion ? fusions : loops).push(...centre(q), ...centre(c));
    }
    for (const [list, colour] of [[loops, 0xffe14d], [fusions, 0xff4dd2]]) {
      if (!list.length) continue;
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.Float32BufferAttribute(list, 3));
      overlay.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: colour })));
    }
    markFresh();
  }

  // Until the user moves the camera, it keeps the whole world map in view as it grows: it
  // looks at what the keyframes look at (1.5 m in front of them, on average) from above and
  // behind, far enough for their spread.
  function frameMap() {
    const primary = primaryMap();
    const centre = new THREE.Vector3(), ahead = new THREE.Vector3(), lo = new THREE.Vector3(Infinity, Infinity, Infinity);
    const hi = new THREE.Vector3(-Infinity, -Infinity, -Infinity);
    let n = 0;
    for (const kf of S.keyframes.values()) {
      if (kf.m !== primary || kf.unplaced) continue;
      const p = new THREE.Vector3(kf.T[3], kf.T[7], kf.T[11]);
      const forward = new THREE.Vector3(kf.T[2], kf.T[6], kf.T[10]);
      centre.add(p).addScaledVector(forward, 1.5);
      ahead.add(forward);
      lo.min(p);
      hi.max(p);
      ++n;
    }
    if (!n) return;
    centre.divideScalar(n);
    const look = ahead.lengthSq() > 0.01 * n * n ? ahead.normalize() : new THREE.Vector3(0, 0, 1);
    const distance = Math.max(3, 1.2 * hi.distanceTo(lo) + 2.5);
    controls.target.copy(centre);
    camera.position.copy(centre).addScaledVector(look, -0.6 * distance).addScaledVector(camera.up, 0.8 * distance);
    controls.update();
    markFresh();
  }

  // ------------------------------------------------------------------ clouds

  const cloudQueue = [];
  let cloudRequests = 0;

  function wantCloud(kf) {
    if (kf.loaded || kf.fetching) return;
    kf.fetching = true;
    cloudQueue.push(kf);
    pumpClouds();
  }

  function pumpClouds() {
    while (cloudRequests < 2 && cloudQueue.length) {
      const batch = cloudQueue.splice(0, 64);
      cloudRequests++;
      fetch(apiUrl('/api/clouds', { ids: batch.map((kf) => key(kf.a, kf.k)).join(',') }))
        .then(function (r) {
          if (!r.ok) throw new Error('HTTP ' + r.status);
          const timing = /dur=([0-9.]+)/.exec(r.headers.get('Server-Timing') || '');
          if (timing) S.latency.server.push(Number(timing[1]));
          return r.arrayBuffer();
        })
        .then(function (buffer) { parseClouds(buffer); })
        .catch(function () {
          S.cloudErrors++;
          for (const kf of batch) kf.fetching = false;  // fetched again after a reconnect
        })
        .finally(function () { cloudRequests--; pumpClouds(); });
    }
  }

  function parseClouds(buffer) {
    const dv = new DataView(buffer);
    let at = 0;
    while (at + 12 <= buffer.byteLength) {
      const a = dv.getUint16(at, true), found = dv.getUint8(at + 2), k = dv.getUint32(at + 4, true);
      const n = dv.getUint32(at + 8, true);
      at += 12;
      const positions = new Int16Array(buffer, at, n * 3);
      const colours = new Uint8Array(buffer, at + 6 * n, n * 3);
      at += Math.ceil((n * 9) / 4) * 4;
      const kf = S.keyframes.get(key(a, k));
      if (!kf) continue;
      kf.fetching = false;
      if (kf.loaded || !kf.cloud) continue;  // a release overtook the request
      if (found) {
        addCloud(kf, positions, colours, n);
      } else {
        wantCloud(kf);  // released and announced again while the request was out
      }
    }
  }

  // ------------------------------------------------------------------ events

  function applyKeyframe(e) {
    const id = key(e.a, e.k);
    const kf = S.keyframes.get(id) || newKeyframe(e.a, e.k);
    S.keyframes.set(id, kf);
    kf.m = e.m;
    setPose(kf, e.T, 0);
    kf.moves = e.moves || 0;
    // An agent's restarted segment that nothing places yet: its poses are a guess.
    kf.unplaced = e.placed === false;
    kf.culled = e.culled === true;
    // Latency counts from arrival only for keyframes the dense map takes at once (not those
    // that wait for their map to be fused).
    if (e.t && e.primary) kf.arrived = e.t;
    if (e.cloud) { kf.cloud = true; wantCloud(kf); }
    markOverlay();
  }

  function apply(e) {
    switch (e.type) {
      case 'agent':
        S.agents.set(e.a, e.name);
        updatePanel();
        break;
      case 'kf':
        applyKeyframe(e);
        break;
      case 'cloud': {
        S.latency.delivery.push(nowMs() - e.t);
        const kf = S.keyframes.get(key(e.a, e.k));
        if (!kf) break;
        kf.cloud = true;
        kf.ready = e.t;
        kf.told = nowMs();
        if (e.data && !kf.loaded) {
          // The server sent the cloud with the event: no request needed.
          const text = atob(e.data), bytes = new Uint8Array(text.length);
          for (let i = 0; i < text.length; ++i) bytes[i] = text.charCodeAt(i);
          parseClouds(bytes.buffer);
        } else {
          wantCloud(kf);
        }
        break;
      }
      case 'poses':
        for (const item of e.kfs) {
          const kf = S.keyframes.get(key(item[0], item[1]));
          if (!kf) continue;
          kf.m = e.m;
          kf.moves++;
          setPose(kf, item, 2);
        }
        S.pendingPose.push({ t: e.t, src: e.src });
        markOverlay();
        markFresh();
        break;
      case 'placed':
        for (const item of e.kfs) {
          const kf = S.keyframes.get(key(item[0], item[1]));
          if (!kf) continue;
          kf.unplaced = !e.placed;
          if (kf.unplaced && kf.cloud) dropCloud(kf);  // out of the dense map while so
        }
        markOverlay();
        break;
      case 'culled':
        for (const item of e.kfs) {
          const id = key(item[0], item[1]), kf = S.keyframes.get(id);
          if (!kf) continue;
          kf.culled = true;
          if (!kf.cloud) S.keyframes.delete(id);  // nothing left to draw
        }
        S.loops = S.loops.filter((l) => S.keyframes.has(key(l.qa, l.qk)) && S.keyframes.has(key(l.ca, l.ck)) &&
          !S.keyframes.get(key(l.qa, l.qk)).culled && !S.keyframes.get(key(l.ca, l.ck)).culled);
        markOverlay();
        break;
      case 'released':
        for (const item of e.kfs) {
          const id = key(item[0], item[1]), kf = S.keyframes.get(id);
          if (!kf) continue;
          dropCloud(kf);
          if (kf.culled) S.keyframes.delete(id);
        }
        break;
      case 'loop':
        S.loops.push(e);
        if (e.fusion) {
          for (const kf of S.keyframes.values()) if (e.from.indexOf(kf.m) >= 0) kf.m = e.m;
        }
        markOverlay();
        break;
      case 'stats': {
        // The drawing depends on the statistics only through which map is the world map.
        const before = primaryMap();
        S.stats = e.stats;
        S.statsVersion++;
        if (primaryMap() !== before) markOverlay();
        updatePanel();
        break;
      }
      case 'reset':
        reload();
        return;
    }
    updateStatus();
    requestDraw();
  }

  let events = null;

  function setConnection(c) {
    S.connection = c;
    const el = document.getElementById('connection');
    el.className = 'connection ' + c;
    el.textContent = c === 'live' ? 'live' : c === 'gone' ? 'server gone' : 'connecting';
    updateStatus();
  }

  function follow(after) {
    if (events) events.close();
    events = new EventSource(apiUrl('/api/events', { after: after }));
    events.onopen = function () { setConnection('live'); };
    events.onmessage = function (m) {
      const e = JSON.parse(m.data);
      if (m.lastEventId) S.seq = Number(m.lastEventId);
      apply(e);
    };
    events.onerror = function () {
      // EventSource reconnects by itself (with Last-Event-ID), except after an answer that is
      // not a stream (503: too many browsers follow the server): then we try again later.
      if (events.readyState === EventSource.CLOSED) {
        const closed = events;
        setTimeout(function () { if (events === closed) follow(S.seq); }, 3000);
      }
      // Tell the user meanwhile.
      fetch(apiUrl('/api/summary')).then(function (r) {
        if (!r.ok) throw new Error();
        if (S.connection !== 'live') setConnection('connecting');
      }).catch(function () { setConnection('gone'); });
    };
  }

  function reload() {
    if (events) { events.close(); events = null; }
    fetch(apiUrl('/api/state')).then(function (r) {
      if (!r.ok) throw new Error('HTTP ' + r.status);
      return r.json();
    }).then(function (state) {
      clearScene();
      S.keyframes.clear();
      S.agents.clear();
      S.loops = state.loops.slice();
      for (const a of state.agents) S.agents.set(a.a, a.name);
      for (const kf of state.keyframes) applyKeyframe(kf);
      S.stats = state.stats;
      S.statsVersion++;
      S.seq = state.seq;
      markOverlay();
      updatePanel();
      follow(state.seq);
    }).catch(function () {
      setConnection('gone');
      setTimeout(reload, 2000);  // the server may come back: try again
    });
  }

  // ------------------------------------------------------------------ panel

  function formatBytes(b) {
    if (b >= 1e9) return (b / 1e9).toFixed(2) + ' GB';
    if (b >= 1e6) return (b / 1e6).toFixed(2) + ' MB';
    if (b >= 1e3) return (b / 1e3).toFixed(1) + ' kB';
    return b + ' B';
  }

  function sparkline(canvas, values, colour) {
    const ctx = canvas.getContext('2d');
    const w = canvas.width = 140, h = canvas.height = 36;
    ctx.clearRect(0, 0, w, h);
    const shown = values.slice(-60);
    const max = Math.max(1e-9, ...shown);
    ctx.strokeStyle = colour;
    ctx.lineWidth = 2;
    ctx.beginPath();
    shown.forEach(function (v, i) {
      const x = shown.length > 1 ? (i * (w - 2)) / (shown.length - 1) + 1 : w / 2;
      const y = h - 2 - (v / max) * (h - 4);
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.stroke();
  }

  function updatePanel() {
    const stats = S.stats || { agents: [], map_list: [] };
    const names = new Map(S.agents);
    for (const a of stats.agents || []) names.set(a.id, a.name);
    const order = sortAgents(names);
    if (order.join() !== agentOrder.join()) {
      agentOrder = order;
      for (const c of chunks) c.material.uniforms.agentColour.value.set(agentColour(c.agent));
      markOverlay();
      markFresh();
    }
    const maps = document.getElementById('maps');
    maps.innerHTML = '';
    for (const m of stats.map_list || []) {
      const li = document.createElement('li');
      li.className = m.primary ? 'fused' : 'apart';
      const who = m.agents.slice().sort((p, q) => agentOrder.indexOf(p) - agentOrder.indexOf(q))
        .map((a) => names.get(a) || 'agent ' + a).join(', ');
      li.textContent = 'map ' + m.id + (m.primary ? ' (world)' : ' (not fused)') + ': ' + who + ', ' +
        m.keyframes + ' keyframes';
      li.dataset.map = m.id;
      maps.appendChild(li);
    }
    const body = document.querySelector('#agents tbody');
    body.innerHTML = '';
    const rows = (stats.agents || []).slice().sort((p, q) => agentOrder.indexOf(p.id) - agentOrder.indexOf(q.id));
    for (const a of rows) {
      const tr = document.createElement('tr');
      tr.dataset.agent = a.id;
      tr.innerHTML = '<td><span class="swatch"></span></td><td class="name"></td><td class="num keyframes"></td>' +
        '<td class="num bytes"></td><td class="num rate"></td><td><canvas class="spark"></canvas></td>' +
        '<td><button type="button">follow</button></td>';
      tr.querySelector('.swatch').style.background = agentColour(a.id);
      tr.querySelector('.name').textContent = a.name;
      if (!a.connected) {
        const note = document.createElement('span');
        note.className = 'offline';
        note.textContent = 'offline';
        tr.querySelector('.name').appendChild(note);
      }
      tr.querySelector('.keyframes').textContent = String(a.keyframes);
      tr.querySelector('.bytes').textContent = formatBytes(a.bytes);
      tr.querySelector('.rate').textContent = a.rate_kBps.toFixed(1) + ' kB/s';
      sparkline(tr.querySelector('canvas'), a.traffic_kBps || [], agentColour(a.id));
      const button = tr.querySelector('button');
      if (view.follow === a.id) button.className = 'on';
      button.onclick = function () { view.follow = view.follow === a.id ? 0 : a.id; updatePanel(); };
      body.appendChild(tr);
    }
    document.getElementById('totals').textContent = (stats.maps || 0) + ' maps, ' + (stats.keyframes || 0) +
      ' keyframes, ' + (stats.points || 0).toLocaleString('en') + ' points in the dense map';
  }

  function updateStatus() {
    const el = document.getElementById('status');
    let text = '', banner = false;
    if (S.connection === 'gone') {
      text = S.keyframes.size ? 'Server gone: this is the last map it sent. Reconnecting...'
                              : 'Server gone: reconnecting...';
      banner = S.keyframes.size > 0;
    } else if (S.connection === 'connecting' && !S.keyframes.size) {
      text = 'Connecting to the server...';
    } else if (!S.keyframes.size) {
      text = 'No map yet: waiting for the first keyframes of the agents.';
    }
    el.textContent = text;
    el.className = 'status' + (text ? '' : ' hidden') + (banner ? ' banner' : '');
  }

  function updateDetail() {
    const total = view.totalPoints;
    const shown = Math.min(total, view.drawnPoints);
    document.getElementById('detail').textContent = total ? 'drawn: ' + shown.toLocaleString('en') + ' of ' +
      total.toLocaleString('en') + ' view points' + (shown < total ? ' (more as the view rests)' : '') : '';
  }

  // ------------------------------------------------------------------ frames

  function resize() {
    const w = container.clientWidth, h = container.clientHeight;
    renderer.setSize(w, h);
    camera.aspect = w / Math.max(1, h);
    camera.updateProjectionMatrix();
    markFresh();
  }
  window.addEventListener('resize', resize);
  resize();

  function followAgent() {
    let last = null;
    for (const kf of S.keyframes.values()) if (kf.a === view.follow && kf.m === primaryMap() && (!last || kf.k > last.k)) last = kf;
    if (!last) return;
    const goal = new THREE.Vector3(last.T[3], last.T[7], last.T[11]);
    const step = goal.sub(controls.target).multiplyScalar(0.1);
    if (step.lengthSq() < 1e-8) return;
    controls.target.add(step);
    camera.position.add(step);
    controls.update();
  }

  // Marks what the frame just drawn shows, for the latency figures (docs/view.md).
  function noteDrawn(t) {
    for (const kf of S.keyframes.values()) {
      if (kf.loaded && !kf.drawn) {
        kf.drawn = true;
        if (kf.arrived) S.latency.keyframe.push(t - kf.arrived);
        if (kf.arrived && kf.ready) S.latency.backend.push(kf.ready - kf.arrived);
        if (kf.ready) S.latency.cloud.push(t - kf.ready);
        if (kf.fetched) S.latency.frame.push(t - kf.fetched);
      }
    }
    for (const p of S.pendingPose) S.latency.pose.push({ ms: t - p.t, src: p.src });
    S.pendingPose = [];
    for (const list of Object.values(S.latency)) {
      if (list.length > 20000) list.splice(0, list.length - 20000);
    }
  }

  // Frames are drawn on demand: nothing runs while nothing changes (a software renderer shares
  // the processor with everything else, the server and agents included).
  function requestDraw() {
    if (frameRequested) return;
    frameRequested = true;
    requestAnimationFrame(frame);
  }
  function markFresh() {
    view.fresh = true;
    requestDraw();
  }

  function frame() {
    frameRequested = false;
    const overlayChanged = overlayDirty;
    if (overlayDirty) rebuildOverlay();
    if (!view.userMoved && !view.follow && overlayChanged) frameMap();
    if (view.follow) {
      followAgent();
      requestDraw();
    }
    // While data keeps coming, the image stays at the coarse levels; the rest is added once
    // nothing changed for a moment.
    const quiet = performance.now() - view.changedAt;
    if (!view.fresh && (!view.refine.length || quiet < REFINE_AFTER_MS)) {
      if (view.refine.length) setTimeout(requestDraw, REFINE_AFTER_MS - quiet);
      view.lastRendered = false;
      return;
    }
    // Frames back to back (the camera moves, data arrives, the image is refined): the time
    // between them is what one costs, and the budget keeps it near 1/30 s.
    const t = performance.now();
    if (view.lastRendered) adaptBudget(t - view.lastFrame);
    if (view.fresh) {
      view.fresh = false;
      drawFresh();
    } else {
      drawRefinement();
    }
    view.lastRendered = true;
    view.lastFrame = t;
    S.frames++;
    noteDrawn(nowMs());
    updateDetail();
    if (view.fresh || view.refine.length) requestDraw();
  }

  // ------------------------------------------------------------------ controls

  for (const input of document.querySelectorAll('input[name=colour]')) {
    input.addEventListener('change', function () {
      view.byAgent = input.value === 'agent' && input.checked;
      for (const c of chunks) c.material.uniforms.byAgent.value = view.byAgent ? 1 : 0;
      markFresh();
    });
  }
  document.getElementById('pointSize').addEventListener('input', function (e) {
    view.pointSize = Number(e.target.value);
    for (const c of chunks) c.material.uniforms.pointSize.value = view.pointSize;
    markFresh();
  });
  document.getElementById('trajectories').addEventListener('change', function (e) {
    view.showOverlay = e.target.checked;
    markFresh();
  });
  document.getElementById('resetView').addEventListener('click', function () {
    view.userMoved = false;
    frameMap();
  });
  controls.addEventListener('start', function () { view.userMoved = true; });

  // ------------------------------------------------------------------ the page's own state

  function percentile(values, q) {
    if (!values.length) return null;
    const v = values.slice().sort((a, b) => a - b);
    return v[Math.min(v.length - 1, Math.round(q * (v.length - 1)))];
  }

  // For tests and benchmarks (docs/view.md): what the page holds and draws.
  window.ccmdView = {
    state: function () {
      const keyframes = [];
      for (const kf of S.keyframes.values()) {
        keyframes.push({ a: kf.a, k: kf.k, m: kf.m, T: Array.from(kf.T), cloud: kf.cloud, loaded: kf.loaded,
          drawn: kf.drawn, moves: kf.moves, points: kf.points, placed: !kf.unplaced, culled: !!kf.culled });
      }
      const panel = [];
      for (const tr of document.querySelectorAll('#agents tbody tr')) {
        panel.push({ id: Number(tr.dataset.agent), name: tr.querySelector('.name').firstChild.textContent,
          keyframes: Number(tr.querySelector('.keyframes').textContent) });
      }
      return { seq: S.seq, connection: S.connection, frames: S.frames, keyframes: keyframes, panel: panel,
        maps: Array.from(document.querySelectorAll('#maps li')).map((li) => li.textContent),
        status: document.getElementById('status').textContent, statsVersion: S.statsVersion,
        stats: S.stats, loops: S.loops.length, totalPoints: view.totalPoints, budget: view.budget,
        cloudErrors: S.cloudErrors, pendingClouds: cloudQueue.length + cloudRequests,
        // What the buffers hold: drawn clouds and released ones not compacted yet.
        bufferedPoints: chunks.reduce((n, c) => n + c.stored(), 0), loadedPoints: view.loadedPoints,
        chunks: chunks.length };
    },
    // Point i of a keyframe as the page holds it (camera-frame millimetres, as loaded), where it
    // draws it (through the matrix the GPU uses for the keyframe) and the keyframe's pose, read
    // at once.
    drawnPoint: function (a, k, i) {
      const kf = S.keyframes.get(key(a, k));
      if (!kf || !kf.loaded) return null;
      let n = i, levelIndex = 0;
      // Point i of the record went to the level whose range holds it.
      let first = 0;
      for (; levelIndex < LEVEL_ENDS.length; ++levelIndex) {
        const last = levelIndex === LEVEL_ENDS.length - 1 ? kf.points : Math.min(kf.points, Math.ceil(kf.points * LEVEL_ENDS[levelIndex]));
        if (i < last) { n = i - first; break; }
        first = Math.max(first, last);
      }
      const level = kf.chunk.levels[levelIndex];
      const slots = level.points.geometry.attributes.slot.array, pos = level.points.geometry.attributes.position.array;
      let seen = -1;
      for (let j = 0; j < level.count; ++j) {
        if (slots[j] === kf.slot && ++seen === n) {
          const p = [pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]];
          const world = [0, 1, 2].map((r) => { const row = kf.chunk.rows[3 * kf.slot + r]; return row.x * p[0] + row.y * p[1] + row.z * p[2] + row.w; });
          return { held: p, world: world, T: Array.from(kf.T) };
        }
      }
      return null;
    },
    // Milliseconds (docs/view.md): keyframe = arrival at the server to the first frame that
    // draws its points (keyframes of the world map only); backend = arrival to its cloud in
    // the dense store; cloud = that to drawn; delivery = that to the event reaching the page;
    // pose = a pose change's arrival (or computation) to the first frame drawn with it.
    latency: function () {
      const summary = function (list) {
        return { n: list.length, median: percentile(list, 0.5), p95: percentile(list, 0.95), max: percentile(list, 1) };
      };
      const bySource = {};
      for (const p of S.latency.pose) (bySource[p.src] = bySource[p.src] || []).push(p.ms);
      const out = { pose_by_source: {} };
      for (const name of ['keyframe', 'backend', 'cloud', 'delivery', 'fetch', 'frame', 'server']) out[name] = summary(S.latency[name]);
      out.pose = summary(S.latency.pose.map((p) => p.ms));
      for (const src in bySource) out.pose_by_source[src] = summary(bySource[src]);
      return out;
    },
    // Resolves once the page has applied event `seq`, loaded every cloud the server has
    // announced and drawn a frame with them.
    whenSettled: function (seq) {
      return new Promise(function (resolve) {
        (function check() {
          let settled = S.seq >= seq && !cloudQueue.length && !cloudRequests && !view.fresh;
          for (const kf of S.keyframes.values()) settled = settled && (!kf.cloud || kf.drawn);
          if (settled) resolve(S.seq); else requestAnimationFrame(check);
        })();
      });
    },
    // Resolves with the statistics' number once the page has received newer ones than `after`.
    whenStats: function (after) {
      return new Promise(function (resolve) {
        (function check() { if (S.statsVersion > after) resolve(S.statsVersion); else requestAnimationFrame(check); })();
      });
    },
    // Resolves once the image is complete: every point drawn, nothing left to refine.
    whenRested: function () {
      return new Promise(function (resolve) {
        (function check() { if (!view.fresh && !view.refine.length) resolve(S.frames); else requestAnimationFrame(check); })();
      });
    },
    // Resolves once the connection to the server is in state `c` (live, connecting, gone).
    whenConnection: function (c) {
      return new Promise(function (resolve) {
        (function check() { if (S.connection === c) resolve(c); else requestAnimationFrame(check); })();
      });
    },
    // Frames with the camera orbiting the map, each waited for (a one-pixel read), the point
    // budget adapting as in interactive use. lod = false draws every point in each frame.
    benchmark: function (options) {
      const frames = options.frames || 60, warmup = options.warmup || 20, lod = options.lod !== false;
      const gl = renderer.getContext(), pixel = new Uint8Array(4);
      const sync = () => gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
      const saved = view.budget;
      if (!lod) view.budget = Infinity;
      const offset = camera.position.clone().sub(controls.target);
      const times = [], drawn = [];
      sync();
      let last = performance.now();
      for (let f = 0; f < warmup + frames; ++f) {
        const angle = (f * 2 * Math.PI) / 120;
        const o = offset.clone().applyAxisAngle(camera.up, angle);
        camera.position.copy(controls.target).add(o);
        camera.lookAt(controls.target);
        drawFresh();
        sync();
        const now = performance.now();
        if (lod) adaptBudget(now - last);
        if (f >= warmup) { times.push(now - last); drawn.push(view.drawnPoints); }
        last = now;
      }
      // The camera rests: refinement frames until every point is drawn.
      let refineFrames = 0;
      const refineStart = performance.now();
      while (view.refine.length) { drawRefinement(); sync(); refineFrames++; }
      const refineMs = performance.now() - refineStart;
      const budget = view.budget;
      if (!lod) view.budget = saved;
      camera.position.copy(controls.target).add(offset);
      controls.update();
      markFresh();
      const total = times.reduce((s, v) => s + v, 0);
      return { frames: times.length, fps: (1000 * times.length) / total, mean_ms: total / times.length,
        p95_ms: percentile(times, 0.95), drawn_points: drawn.reduce((s, v) => s + v, 0) / drawn.length,
        total_points: view.totalPoints, budget: budget, refine_frames: refineFrames, refine_ms: refineMs };
    },
  };

  updateStatus();
  reload();
  requestDraw();
})();
