// Test vectors for crowd.asset.gltf.meshopt, made by meshoptimizer's own encoder and decoder (the npm
// package "meshoptimizer", pinned below). Run from a folder where `npm install meshoptimizer@1.3.0`
// was done:  node make_vectors.mjs | gzip -9n > vectors.json.gz
// The inputs are deterministic (a fixed linear congruential generator), so the file is reproducible.
import { MeshoptEncoder as E, MeshoptDecoder as D } from 'meshoptimizer';

await E.ready;
await D.ready;

let seed = 12345;
const rand = () => ((seed = (Math.imul(seed, 1103515245) + 12345) >>> 0) / 4294967296);
const b64 = (u8) => Buffer.from(u8.buffer, u8.byteOffset, u8.byteLength).toString('base64');
const out = [];

function emit(name, mode, filter, count, stride, encoded) {
	const target = new Uint8Array(count * stride);
	D.decodeGltfBuffer(target, count, stride, encoded, mode, filter);
	out.push({ name, mode, filter, count, stride, version: mode === 'ATTRIBUTES' ? encoded[0] & 15 : null,
		encoded: b64(encoded), decoded: b64(target) });
}

// Attribute data of several kinds: small smooth deltas, float positions, noise, constants, rare jumps.
function attributes(kind, count, stride) {
	const u8 = new Uint8Array(count * stride);
	const f32 = new Float32Array(u8.buffer);
	for (let i = 0; i < count; i++) {
		for (let k = 0; k < stride; k++) {
			const at = i * stride + k;
			if (kind === 'smooth') u8[at] = (i * (k + 1) + (k * 37)) & 255;
			else if (kind === 'noise') u8[at] = (rand() * 256) | 0;
			else if (kind === 'constant') u8[at] = (k * 13) & 255;
			else if (kind === 'jumps') u8[at] = (i + (rand() < 0.1 ? (rand() * 256) | 0 : 0)) & 255;
			else if (kind === 'shorts' && k % 2 === 0) { const v = (Math.sin(i * 0.05 + k) * 20000) | 0; u8[at] = v & 255; u8[at + 1] = (v >> 8) & 255; }
		}
		if (kind === 'floats') for (let c = 0; c < stride / 4; c++) f32[i * stride / 4 + c] = Math.sin(i * 0.01 * (c + 1)) * (c + 1) * 1.7;
	}
	return u8;
}

for (const version of [0, 1])
	for (const [kind, stride, count] of [['smooth', 4, 1], ['smooth', 8, 15], ['smooth', 12, 16], ['jumps', 16, 17],
		['noise', 4, 300], ['constant', 20, 257], ['floats', 12, 520], ['floats', 16, 520], ['shorts', 8, 520],
		['jumps', 64, 140], ['smooth', 256, 33], ['noise', 24, 129], ['floats', 4, 600]])
		for (const level of version ? [2, 3] : [2]) {
			const data = attributes(kind, count, stride);
			emit(`v${version} ${kind} stride ${stride} count ${count} level ${level}`, 'ATTRIBUTES', 'NONE', count, stride,
				E.encodeVertexBufferLevel(data, count, stride, level, version));
		}

// Filters: unit vectors, quaternions, floats, colours; encoded by the filter encoders, then the codec.
function units(count, stride4) {
	const v = new Float32Array(count * stride4);
	for (let i = 0; i < count; i++) {
		const x = rand() * 2 - 1, y = rand() * 2 - 1, z = rand() * 2 - 1, n = Math.hypot(x, y, z) || 1;
		v.set([x / n, y / n, z / n, rand() < 0.5 ? -1 : 1].slice(0, stride4), i * stride4);
	}
	return v;
}
for (const version of [0, 1]) {
	for (const [stride, bits] of [[4, 8], [4, 5], [8, 16], [8, 12]]) {
		const count = 300;
		emit(`v${version} octahedral stride ${stride} bits ${bits}`, 'ATTRIBUTES', 'OCTAHEDRAL', count, stride,
			E.encodeGltfBuffer(E.encodeFilterOct(units(count, 4), count, stride, bits), count, stride, 'ATTRIBUTES', version));
	}
	for (const bits of [16, 12, 9]) {
		const count = 300;
		emit(`v${version} quaternion bits ${bits}`, 'ATTRIBUTES', 'QUATERNION', count, 8,
			E.encodeGltfBuffer(E.encodeFilterQuat(units(count, 4), count, 8, bits), count, 8, 'ATTRIBUTES', version));
	}
	for (const [mode, bits] of [['Separate', 15], ['SharedVector', 23], ['SharedComponent', 10], ['Clamped', 12]]) {
		const count = 300, stride = 12, f = new Float32Array(count * 3);
		for (let i = 0; i < f.length; i++) f[i] = (rand() - 0.5) * Math.pow(10, (i % 7) - 3);
		emit(`v${version} exponential ${mode} bits ${bits}`, 'ATTRIBUTES', 'EXPONENTIAL', count, stride,
			E.encodeGltfBuffer(E.encodeFilterExp(f, count, stride, bits, mode), count, stride, 'ATTRIBUTES', version));
	}
}
for (const [stride, bits] of [[4, 8], [4, 6], [8, 16], [8, 11]]) {
	const count = 200, f = new Float32Array(count * 4);
	for (let i = 0; i < f.length; i++) f[i] = rand();
	emit(`v1 color stride ${stride} bits ${bits}`, 'ATTRIBUTES', 'COLOR', count, stride,
		E.encodeGltfBuffer(E.encodeFilterColor(f, count, stride, bits), count, stride, 'ATTRIBUTES', 1));
}

// Triangles: a vertex-cache ordered grid (most codes one byte), random triangles (explicit indices),
// two grids concatenated (the `next` restart), both index widths.
function grid(w, h, base = 0) {
	const idx = [];
	for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
		const a = base + y * (w + 1) + x, b = a + 1, c = a + w + 1, d = c + 1;
		idx.push(a, c, b, b, c, d);
	}
	return idx;
}
const cases = [['grid 12x10', grid(12, 10)], ['grid 3x1', grid(3, 1)], ['one triangle', [0, 1, 2]],
	['random', Array.from({ length: 300 }, () => (rand() * 400) | 0)],
	['two grids', [...grid(8, 8), ...grid(8, 8, 81)]]];
for (const [name, list] of cases) {
	let indices = new Uint32Array(list);
	if (name.startsWith('grid') || name === 'two grids') {
		const [remap] = E.reorderMesh(indices.slice(), true, false);
		indices = new Uint32Array(list.map((i) => remap[i]));
	}
	for (const stride of [2, 4]) {
		const data = stride === 2 ? new Uint8Array(new Uint16Array(indices).buffer) : new Uint8Array(indices.buffer.slice(0));
		emit(`triangles ${name} stride ${stride}`, 'TRIANGLES', 'NONE', indices.length, stride,
			E.encodeGltfBuffer(data, indices.length, stride, 'TRIANGLES'));
	}
}
// Indices: a strip-like bimodal sequence, random values with large jumps, both widths.
const strip = Array.from({ length: 500 }, (_, i) => (i % 2 ? 1000 + (i >> 1) : (i >> 1)));
const wild = Array.from({ length: 300 }, () => (rand() * 4e9) >>> 0);
for (const [name, list, strides] of [['strip', strip, [2, 4]], ['wild', wild, [4]]])
	for (const stride of strides) {
		const data = stride === 2 ? new Uint8Array(new Uint16Array(list).buffer) : new Uint8Array(new Uint32Array(list).buffer);
		emit(`indices ${name} stride ${stride}`, 'INDICES', 'NONE', list.length, stride,
			E.encodeGltfBuffer(data, list.length, stride, 'INDICES'));
	}

process.stdout.write(JSON.stringify({ made_by: 'meshoptimizer 1.3.0 (npm)', vectors: out }, null, 0));
