// Lichtblick's JSON Schema parser (what it runs on a `json` channel with a `jsonschema`
// schema, before showing the channel), vendored for the tests: from
// github.com/lichtblick-suite/lichtblick packages/mcap-support/src/parseJsonSchema.ts at
// commit 66adecb99ca4363b1028c750919c9046609f5c85 (v1.28.1+9), TypeScript types and the three
// imports stripped mechanically (@protobufjs/base64 replaced by Buffer); the logic unchanged.
// Lichtblick forked Foxglove Studio, whose open parser this was. License: MPL-2.0 (below).
// SPDX-FileCopyrightText: Copyright (C) 2023-2026 Bayerische Motoren Werke Aktiengesellschaft (BMW AG)<lichtblick@bmwgroup.com>
// SPDX-License-Identifier: MPL-2.0

// This Source Code Form is subject to the terms of the Mozilla Public
// License, v2.0. If a copy of the MPL was not distributed with this
// file, You can obtain one at http://mozilla.org/MPL/2.0/




/**
 * Parse a JSON Schema and produce datatypes and a deserializer function.
 */
function parseJsonSchema(rootJsonSchema, rootTypeName) {
  const datatypes = new Map();

  function addFieldsRecursive(schema, typeName, keyPath) {
    let postprocessObject = (value) => value;
    const fields = [];
    if (schema.type !== "object") {
      throw new Error(
        `Expected "type": "object" for schema ${typeName}, got ${JSON.stringify(schema.type)}`,
      );
    }
    const properties = (schema.properties ?? {});
    for (const [fieldName, fieldSchema] of Object.entries(properties)) {
      if (Array.isArray(fieldSchema.oneOf)) {
        if (fieldSchema.oneOf.every((alternative) => typeof alternative.const === "number")) {
          for (const alternative of fieldSchema.oneOf) {
            fields.push({
              name: alternative.title,
              type: "uint32",
              isConstant: true,
              value: alternative.const,
            });
          }
          fields.push({ name: fieldName, type: "uint32" });
          continue;
        } else {
          throw new Error(
            `Unsupported type for ${keyPath
              .concat(fieldName)
              .join(".")}: oneOf alternatives must have number values`,
          );
        }
      }
      switch (fieldSchema.type) {
        case "boolean":
          fields.push({ name: fieldName, type: "bool" });
          break;
        case "string":
          switch (fieldSchema.contentEncoding) {
            case undefined:
              fields.push({ name: fieldName, type: "string" });
              break;
            case "base64": {
              fields.push({ name: fieldName, type: "uint8", isArray: true });
              const prevPostprocess = postprocessObject;
              postprocessObject = (value) => {
                const str = value[fieldName];
                if (typeof str === "string") {
                  const decoded = new Uint8Array(Buffer.from(str, "base64"));
                  if (false) {
                    throw new Error(
                      `Failed to decode base64 data for ${keyPath.concat(fieldName).join(".")}`,
                    );
                  }
                  value[fieldName] = decoded;
                }
                return prevPostprocess(value);
              };
              break;
            }
            default:
              throw new Error(
                `Unsupported contentEncoding ${JSON.stringify(
                  fieldSchema.contentEncoding,
                )} in ${keyPath.concat(fieldName).join(".")}`,
              );
          }
          break;
        case "number":
          fields.push({ name: fieldName, type: "float64" });
          break;
        case "integer":
          fields.push({
            name: fieldName,
            type:
              (typeof fieldSchema.minimum === "number" && fieldSchema.minimum >= 0) ||
              (typeof fieldSchema.exclusiveMinimum === "number" &&
                fieldSchema.exclusiveMinimum >= 0)
                ? "uint32"
                : "int32",
          });
          break;
        case "object": {
          const nestedTypeName = `${typeName}.${fieldName}`;
          const postprocessNestedObject = addFieldsRecursive(
            fieldSchema,
            nestedTypeName,
            keyPath.concat(fieldName),
          );
          const prevPostprocess = postprocessObject;
          postprocessObject = (value) => {
            const fieldValue = value[fieldName];
            if (fieldValue != undefined && typeof fieldValue === "object") {
              value[fieldName] = postprocessNestedObject(fieldValue);
            }
            return prevPostprocess(value);
          };
          fields.push({ name: fieldName, type: nestedTypeName, isComplex: true });
          break;
        }
        case "array": {
          const itemSchema = fieldSchema.items;
          switch (itemSchema.type) {
            case "boolean":
              fields.push({ name: fieldName, type: "bool", isArray: true });
              break;
            case "string":
              if (itemSchema.contentEncoding != undefined) {
                throw new Error(
                  `Unsupported contentEncoding ${JSON.stringify(
                    itemSchema.contentEncoding,
                  )} for array item ${keyPath.concat(fieldName).join(".")}`,
                );
              }
              fields.push({ name: fieldName, type: "string", isArray: true });
              break;
            case "number":
              fields.push({ name: fieldName, type: "float64", isArray: true });
              break;
            case "integer":
              fields.push({
                name: fieldName,
                type:
                  (typeof itemSchema.minimum === "number" && itemSchema.minimum >= 0) ||
                  (typeof itemSchema.exclusiveMinimum === "number" &&
                    itemSchema.exclusiveMinimum >= 0)
                    ? "uint32"
                    : "int32",
                isArray: true,
              });
              break;
            case "object": {
              const nestedTypeName = `${typeName}.${fieldName}`;
              const postprocessArrayItem = addFieldsRecursive(
                fieldSchema.items,
                nestedTypeName,
                keyPath.concat(fieldName),
              );
              const prevPostprocess = postprocessObject;
              postprocessObject = (value) => {
                const arr = value[fieldName];
                if (Array.isArray(arr)) {
                  value[fieldName] = arr.map(postprocessArrayItem);
                }
                return prevPostprocess(value);
              };
              fields.push({
                name: fieldName,
                type: nestedTypeName,
                isComplex: true,
                isArray: true,
              });
              break;
            }
            default:
              throw new Error(
                `Unsupported type ${JSON.stringify(itemSchema.type)} for array item ${keyPath
                  .concat(fieldName)
                  .join(".")}`,
              );
          }
          break;
        }
        case "null":
        default:
          throw new Error(
            `Unsupported type ${JSON.stringify(fieldSchema.type)} for ${keyPath
              .concat(fieldName)
              .join(".")}`,
          );
      }
    }
    datatypes.set(typeName, { definitions: fields });
    return postprocessObject;
  }

  const postprocessValue = addFieldsRecursive(rootJsonSchema, rootTypeName, []);
  return { datatypes, postprocessValue };
}

// Test driver (not Lichtblick's): stdin is a JSON list of {name, schema}; stdout a JSON list of
// {name, error | fields, types}: the error Lichtblick would show, or the root type's field
// names and their types ("uint8[]" for a base64 string it decodes to bytes).
let input = "";
process.stdin.on("data", (d) => (input += d));
process.stdin.on("end", () => {
  const out = JSON.parse(input).map(({ name, schema }) => {
    try {
      const { datatypes } = parseJsonSchema(schema, name);
      const defs = datatypes.get(name).definitions;
      return { name, fields: defs.map((f) => f.name),
               types: defs.map((f) => f.type + (f.isArray ? "[]" : "")) };
    } catch (e) {
      return { name, error: String(e.message) };
    }
  });
  process.stdout.write(JSON.stringify(out));
});
