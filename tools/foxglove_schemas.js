// Generates the Foxglove message definitions memlog writes, with the generators shipped in the
// @foxglove/schemas npm package (dist/internal) and its JSON schemas (dist/jsonschema).
//
// Usage: node tools/foxglove_schemas.js PACKAGE_DIR   (PACKAGE_DIR: the unpacked tarball's "package")
// Prints one JSON object {relative path: file text} on stdout. Run through tools/foxglove_schemas.py,
// which fetches and checks the tarball, compiles the .proto files and writes memlog/outputs/foxglove/.
"use strict";

const path = require("path");
const Module = require("module");

const MESSAGES = ["ImageAnnotations", "CompressedImage"];

const pkg = path.resolve(process.argv[2] || "package");

// generateRos.js requires @foxglove/rosmsg-msgs-common for schemas that embed standard ROS types
// (rosEquivalent). None of MESSAGES does; a stub that throws on any use proves it, so the package's
// dependencies need not be installed.
const loadModule = Module._load;
Module._load = function (request, parent, isMain) {
  if (request === "@foxglove/rosmsg-msgs-common") {
    const refuse = new Proxy({}, {
      get(_target, key) {
        throw new Error(`@foxglove/rosmsg-msgs-common used (${String(key)}): install it to generate this schema`);
      },
    });
    return { ros1: refuse, ros2galactic: refuse, ros2humble: refuse, ros2jazzy: refuse };
  }
  return loadModule.call(this, request, parent, isMain);
};

const { foxgloveMessageSchemas, foxgloveEnumSchemas } = require(path.join(pkg, "dist/internal/schemas.js"));
const { generateRosMsgMergedSchema } = require(path.join(pkg, "dist/internal/generateRos.js"));
const { generateProto } = require(path.join(pkg, "dist/internal/generateProto.js"));
const jsonschema = require(path.join(pkg, "dist/jsonschema/index.js"));

// Foxglove schemas a message refers to (itself first); Timestamp/Duration map to google.protobuf.
function protoDependencies(schema, seen) {
  if (seen.has(schema.name) || schema.protoEquivalent !== undefined) {
    return;
  }
  seen.add(schema.name);
  for (const field of schema.fields) {
    if (field.type.type === "nested") {
      protoDependencies(field.type.schema, seen);
    }
  }
}

const out = {};
for (const name of MESSAGES) {
  const schema = foxgloveMessageSchemas[name];
  if (schema === undefined || jsonschema[name] === undefined) {
    throw new Error(`@foxglove/schemas has no message ${name}`);
  }
  out[`jsonschema/foxglove.${name}.json`] = JSON.stringify(jsonschema[name], null, 2) + "\n";
  out[`ros1msg/foxglove_msgs/${name}.msg`] = generateRosMsgMergedSchema(schema, { rosVersion: 1 });
  out[`ros2msg/foxglove_msgs/msg/${name}.msg`] = generateRosMsgMergedSchema(schema, { rosVersion: 2 });
  const deps = new Set();
  protoDependencies(schema, deps);
  for (const dep of deps) {
    const depSchema = foxgloveMessageSchemas[dep];
    const enums = Object.values(foxgloveEnumSchemas).filter((e) => e.parentSchemaName === dep);
    out[`proto/foxglove/${dep}.proto`] = generateProto(depSchema, enums);
  }
}
process.stdout.write(JSON.stringify(out));
