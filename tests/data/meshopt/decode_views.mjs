// What meshoptimizer's own decoder makes of each compressed bufferView of the gltfpack copies:
//   node decode_views.mjs zombie_ext.glb zombie_khr.glb | gzip -9n > zombie_views.json.gz
// Each view's SHA-256, and for the octahedral and quaternion filters (which the extensions specify to
// one unit in the last place) the decoded bytes themselves.
import { MeshoptDecoder as D } from 'meshoptimizer';
import crypto from 'crypto';
import fs from 'fs';
await D.ready;
const result = {};
for (const file of process.argv.slice(2)) {
	const data = fs.readFileSync(file);
	const jsonLen = data.readUInt32LE(12);
	const doc = JSON.parse(data.subarray(20, 20 + jsonLen).toString());
	const bin = data.subarray(28 + jsonLen);
	result[file.split('/').pop()] = doc.bufferViews.map((view, index) => {
		const ext = (view.extensions || {}).EXT_meshopt_compression || (view.extensions || {}).KHR_meshopt_compression;
		if (!ext) return null;
		const bytes = new Uint8Array(ext.count * ext.byteStride);
		const at = ext.byteOffset || 0;
		D.decodeGltfBuffer(bytes, ext.count, ext.byteStride, bin.subarray(at, at + ext.byteLength), ext.mode, ext.filter);
		const entry = { index, filter: ext.filter || 'NONE', sha256: crypto.createHash('sha256').update(bytes).digest('hex') };
		if (entry.filter === 'OCTAHEDRAL' || entry.filter === 'QUATERNION') entry.decoded = Buffer.from(bytes).toString('base64');
		return entry;
	}).filter((e) => e);
}
process.stdout.write(JSON.stringify({ made_by: 'meshoptimizer 1.3.0 (npm)', files: result }));
