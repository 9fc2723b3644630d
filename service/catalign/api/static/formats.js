/*
 * Point cloud files read in the browser, only to draw them: readCloud(file) gives a Float32Array
 * of x, y, z (finite points only), or null when the format or its variant is not read here.
 *
 * .npy: float32/float64 arrays of shape (N, 3), either byte order, C or Fortran order.
 * .xyz: text, the first three numbers of each line.
 * .ply: the vertex element's x, y, z; ascii, binary_little_endian or binary_big_endian (binary
 *       files only when every element before the vertices has fixed-size rows).
 * .pcd: x, y, z fields; DATA ascii or binary (binary_compressed is not read).
 * The server reads these formats itself; the page uploads the file unchanged.
 */


export async function readCloud(file) {
  const parsers = { npy: parseNpy, xyz: parseXyz, ply: parsePly, pcd: parsePcd };
  const parse = parsers[file.name.split('.').pop().toLowerCase()];
  try {
    const points = parse ? parse(await file.arrayBuffer()) : null;
    return points && points.length > 0 ? finiteOnly(points) : null;
  } catch {
    return null;
  }
}

function finiteOnly(points) {
  const kept = [];
  for (let i = 0; i + 2 < points.length; i += 3) {
    const point = points.subarray(i, i + 3);
    if (point.every(Number.isFinite)) kept.push(...point);
  }
  return kept.length === points.length ? points : new Float32Array(kept);
}

export function readFloats(data, offset, count, size, littleEndian) {
  const out = new Float32Array(count);
  for (let i = 0; i < count; i++) {
    const at = offset + i * size;
    out[i] = size === 8 ? data.getFloat64(at, littleEndian) : data.getFloat32(at, littleEndian);
  }
  return out;
}

function parseNpy(buffer) {
  // Format: \x93NUMPY, version, header length, a Python dict literal, then the raw array.
  const bytes = new Uint8Array(buffer);
  const data = new DataView(buffer);
  if (bytes[0] !== 0x93 || latin1(bytes.subarray(1, 6)) !== 'NUMPY') return null;
  const headerStart = bytes[6] === 1 ? 10 : 12;
  const headerLength = bytes[6] === 1 ? data.getUint16(8, true) : data.getUint32(8, true);
  const header = latin1(bytes.subarray(headerStart, headerStart + headerLength));
  const dtype = /'descr':\s*'([<>|=])f([48])'/.exec(header);
  const shape = /'shape':\s*\((\d+),\s*3,?\s*\)/.exec(header);
  if (!dtype || !shape) return null;
  const [size, rows] = [Number(dtype[2]), Number(shape[1])];
  const points = readFloats(data, headerStart + headerLength, rows * 3, size, dtype[1] !== '>');
  return /'fortran_order':\s*True/.test(header) ? transposeColumns(points, rows) : points;
}

function transposeColumns(columns, rows) {
  const points = new Float32Array(rows * 3);
  for (let i = 0; i < rows; i++) {
    for (let j = 0; j < 3; j++) points[i * 3 + j] = columns[j * rows + i];
  }
  return points;
}

function parseXyz(buffer) {
  const values = [];
  for (const line of new TextDecoder().decode(buffer).split('\n')) {
    const fields = line.trim().split(/[\s,]+/).slice(0, 3).map(Number);
    if (fields.length === 3 && fields.every(Number.isFinite)) values.push(...fields);
  }
  return new Float32Array(values);
}

const PLY_TYPES = {
  char: ['Int8', 1], int8: ['Int8', 1], uchar: ['Uint8', 1], uint8: ['Uint8', 1],
  short: ['Int16', 2], int16: ['Int16', 2], ushort: ['Uint16', 2], uint16: ['Uint16', 2],
  int: ['Int32', 4], int32: ['Int32', 4], uint: ['Uint32', 4], uint32: ['Uint32', 4],
  float: ['Float32', 4], float32: ['Float32', 4], double: ['Float64', 8], float64: ['Float64', 8],
};

function parsePly(buffer) {
  // The vertex element's x, y, z; elements before it are skipped (binary: fixed-size rows only).
  const bytes = new Uint8Array(buffer);
  const head = latin1(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const end = /end_header\r?\n/.exec(head);
  if (!head.startsWith('ply') || !end) return null;
  const lines = head.slice(0, end.index).split(/\r?\n/).map((l) => l.trim().split(/\s+/));
  const format = lines.find((l) => l[0] === 'format')?.[1];
  const elements = plyElements(lines);
  const body = end.index + end[0].length;
  if (format === 'ascii') return plyAscii(buffer, body, elements);
  if (format === 'binary_little_endian' || format === 'binary_big_endian') {
    return plyBinary(new DataView(buffer), body, elements, format === 'binary_little_endian');
  }
  return null;
}

function plyElements(lines) {
  const elements = [];
  for (const [keyword, ...rest] of lines) {
    if (keyword === 'element') {
      elements.push({ name: rest[0], count: Number(rest[1]), properties: [] });
    }
    if (keyword === 'property' && elements.length > 0) {
      const list = rest[0] === 'list';
      elements.at(-1).properties.push({ name: rest.at(-1), type: list ? null : rest[0], list });
    }
  }
  return elements;
}

function plyAscii(buffer, body, elements) {
  const rows = new TextDecoder().decode(new Uint8Array(buffer, body)).split('\n');
  let row = 0;
  for (const element of elements) {
    if (element.name === 'vertex') {
      return pickColumns(rows.slice(row, row + element.count), element.properties);
    }
    row += element.count;
  }
  return null;
}

function pickColumns(rows, properties) {
  const names = properties.map((p) => p.name);
  const [x, y, z] = ['x', 'y', 'z'].map((n) => names.indexOf(n));
  if (Math.min(x, y, z) < 0 || properties.some((p) => p.list)) return null;
  const points = new Float32Array(rows.length * 3);
  rows.forEach((line, i) => {
    const fields = line.trim().split(/\s+/);
    points.set([Number(fields[x]), Number(fields[y]), Number(fields[z])], i * 3);
  });
  return points;
}

function plyBinary(data, body, elements, littleEndian) {
  let offset = body;
  for (const element of elements) {
    if (element.properties.some((p) => p.list || !PLY_TYPES[p.type])) return null;
    const layout = recordLayout(element.properties.map((p) => [p.name, ...PLY_TYPES[p.type]]));
    if (element.name === 'vertex') {
      return readRecords(data, offset, element.count, layout, littleEndian);
    }
    offset += element.count * layout.stride;
  }
  return null;
}

function recordLayout(fields) {
  // fields: [name, DataView getter suffix, byte size] per value, in file order.
  const layout = { stride: 0, columns: {} };
  for (const [name, getter, size] of fields) {
    layout.columns[name] ??= { offset: layout.stride, getter };
    layout.stride += size;
  }
  return layout;
}

function readRecords(data, offset, count, layout, littleEndian) {
  const columns = ['x', 'y', 'z'].map((n) => layout.columns[n]);
  if (columns.some((c) => !c) || offset + count * layout.stride > data.byteLength) return null;
  const points = new Float32Array(count * 3);
  for (let i = 0; i < count; i++) {
    const record = offset + i * layout.stride;
    columns.forEach((column, j) => {
      const read = data[`get${column.getter}`].bind(data); // getFloat32, getInt16, ...
      points[i * 3 + j] = read(record + column.offset, littleEndian);
    });
  }
  return points;
}

const PCD_TYPES = {
  F4: 'Float32', F8: 'Float64', I1: 'Int8', I2: 'Int16', I4: 'Int32',
  U1: 'Uint8', U2: 'Uint16', U4: 'Uint32',
};

function parsePcd(buffer) {
  // Header lines up to DATA; ascii rows or binary records (binary_compressed is not read here).
  const bytes = new Uint8Array(buffer);
  const head = latin1(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const dataLine = /^DATA\s+(\S+)[^\n]*\n/m.exec(head);
  if (!dataLine) return null;
  const header = {};
  for (const line of head.slice(0, dataLine.index).split('\n')) {
    const [key, ...values] = line.trim().split(/\s+/);
    if (key && !key.startsWith('#')) header[key.toUpperCase()] = values;
  }
  const fields = pcdFields(header);
  const [width, height] = [Number(header.WIDTH?.[0]), Number(header.HEIGHT?.[0] ?? 1)];
  const count = Number(header.POINTS?.[0] ?? width * height);
  const body = dataLine.index + dataLine[0].length;
  if (dataLine[1] === 'ascii') {
    const text = new TextDecoder().decode(new Uint8Array(buffer, body));
    const rows = text.split('\n').filter((line) => line.trim());
    return pickColumns(rows.slice(0, count), fields.map((f) => ({ name: f[0], list: false })));
  }
  if (dataLine[1] !== 'binary' || fields.some((f) => !f[1])) return null;
  return readRecords(new DataView(buffer), body, count, recordLayout(fields), true);
}

function pcdFields(header) {
  // One [name, DataView getter suffix, byte size] per value (a field with COUNT n gives n).
  const names = header.FIELDS ?? header.COLUMNS ?? [];
  const fields = [];
  names.forEach((name, i) => {
    const size = Number(header.SIZE?.[i] ?? 4);
    const getter = PCD_TYPES[`${header.TYPE?.[i] ?? 'F'}${size}`];
    for (let k = 0; k < Number(header.COUNT?.[i] ?? 1); k++) {
      fields.push([k === 0 ? name : `${name}_${k}`, getter, size]);
    }
  });
  return fields;
}

function latin1(bytes) {
  return new TextDecoder('latin1').decode(bytes);
}
