"""protoc-gen-behaviorlib (proto/codegen): a behavior declared by its
parameters message gets its requests and typed service generated; a bad
declaration is refused with a message that names the file, the message and
the mistake.

Runs Debian's protoc with the built plugin on declarations written here, in a
package of their own (as a team outside this repository would), and checks
what protoc then compiles from the output.

  protoc_gen_behaviorlib_test.py --protoc P --plugin G --proto-root DIR
"""

import argparse
import os
import subprocess
import sys
import tempfile
import unittest

from google.protobuf import descriptor_pb2

ARGS = None

HEADER = """syntax = "proto3";
package acme.v1;
import "behaviorlib/v1/options.proto";
"""

GOOD = HEADER + """
// DANCE: moves to the music until the music stops.
message DanceParameters {
  option (behaviorlib.v1.declare) = {
    name: "DANCE"
    kind: BEHAVIOR_KIND_RECURRENT
    pause_doc: "Pauses DANCE: the dancer freezes."
  };
  // Beats per minute.
  optional double tempo_bpm = 1 [(behaviorlib.v1.param) = { range: { min: 1 max: 300 } }];
}

// Not a behavior: left alone.
message Song {
  string title = 1;
}
"""


def run_plugin(tmp, text, name="acme/v1/dance.proto"):
    src = os.path.join(tmp, "src")
    out = os.path.join(tmp, "out")
    os.makedirs(os.path.join(src, os.path.dirname(name)), exist_ok=True)
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(src, name), "w", encoding="utf-8") as f:
        f.write(text)
    return subprocess.run(
        [ARGS.protoc, f"--proto_path={src}", f"--proto_path={ARGS.proto_root}",
         f"--plugin=protoc-gen-behaviorlib={ARGS.plugin}", f"--behaviorlib_out={out}",
         os.path.join(src, name)],
        capture_output=True, text=True, timeout=60, check=False), src, out


class GeneratesTheApi(unittest.TestCase):
    def test_a_declaration_becomes_requests_and_a_typed_service(self):
        with tempfile.TemporaryDirectory() as tmp:
            result, src, out = run_plugin(tmp, GOOD)
            self.assertEqual(result.returncode, 0, result.stderr)
            generated = os.path.join(out, "acme/v1/dance_services.proto")
            header = os.path.join(out, "acme/v1/dance.behaviors.h")
            with open(header, encoding="utf-8") as f:
                self.assertIn("Dance behaviorServiceOf(const DanceParameters*);", f.read())
            self.assertIn("namespace acme::v1 {", open(header, encoding="utf-8").read())
            # What protoc makes of the generated file: it must compile, with
            # the declaration's comment and docs in it.
            descriptor_set = os.path.join(tmp, "set.pb")
            compiled = subprocess.run(
                [ARGS.protoc, f"--proto_path={out}", f"--proto_path={src}",
                 f"--proto_path={ARGS.proto_root}", "--include_source_info",
                 f"--descriptor_set_out={descriptor_set}", generated],
                capture_output=True, text=True, timeout=60, check=False)
            self.assertEqual(compiled.returncode, 0, compiled.stderr)
            files = descriptor_pb2.FileDescriptorSet()
            with open(descriptor_set, "rb") as f:
                files.ParseFromString(f.read())
            (file,) = files.file
            self.assertEqual(file.package, "acme.v1")
            self.assertEqual([m.name for m in file.message_type],
                             ["DanceActivateRequest", "DanceModifyRequest"])
            (service,) = file.service
            self.assertEqual(service.name, "Dance")
            methods = {m.name: (m.input_type, m.output_type) for m in service.method}
            self.assertEqual(set(methods), {"Activate", "Deactivate", "CheckActivation",
                                            "CheckSituation", "Pause", "Resume", "Modify"})
            self.assertEqual(methods["Activate"], (".acme.v1.DanceActivateRequest",
                                                   ".behaviorlib.v1.ActivateResponse"))
            self.assertEqual(methods["Modify"][0], ".acme.v1.DanceModifyRequest")
            params = file.message_type[0].field[1]
            self.assertEqual((params.name, params.type_name),
                             ("parameters", ".acme.v1.DanceParameters"))
            comments = {tuple(loc.path): loc.leading_comments
                        for loc in file.source_code_info.location}
            service_index = 6  # FileDescriptorProto.service
            self.assertIn("DANCE: moves to the music", comments[(service_index, 0)])
            self.assertIn("Pauses DANCE: the dancer freezes.", comments[(service_index, 0, 2, 4)])
            self.assertIn("Resumes a paused DANCE.", comments[(service_index, 0, 2, 5)])
            # The service option names the behavior (field 51235 of
            # ServiceOptions, unknown to this Python side: check its bytes).
            raw = service.options.SerializeToString()
            self.assertIn(b"DANCE", raw)
            self.assertIn(b"acme.v1.DanceParameters", raw)


class RefusesBadDeclarations(unittest.TestCase):
    def refused(self, text, *expected):
        with tempfile.TemporaryDirectory() as tmp:
            result, _, _ = run_plugin(tmp, text)
        self.assertNotEqual(result.returncode, 0)
        for part in ("acme/v1/dance.proto",) + expected:
            self.assertIn(part, result.stderr)

    def test_a_message_name_without_parameters(self):
        self.refused(HEADER + """message Dance {
  option (behaviorlib.v1.declare) = { name: "DANCE" kind: BEHAVIOR_KIND_RECURRENT };
}""", "Dance declares a behavior but its name does not end in 'Parameters'")

    def test_a_name_not_in_upper_snake_case(self):
        self.refused(HEADER + """message DanceParameters {
  option (behaviorlib.v1.declare) = { name: "Dance" kind: BEHAVIOR_KIND_RECURRENT };
}""", "'Dance': a name is upper snake case")

    def test_a_declaration_without_a_kind(self):
        self.refused(HEADER + """message DanceParameters {
  option (behaviorlib.v1.declare) = { name: "DANCE" };
}""", "declares DANCE without its kind")

    def test_a_file_that_declares_nothing(self):
        self.refused(HEADER + "message Song {}\n", "declares no behavior")


def main():
    global ARGS  # pylint: disable=global-statement
    parser = argparse.ArgumentParser()
    parser.add_argument("--protoc", required=True)
    parser.add_argument("--plugin", required=True)
    parser.add_argument("--proto-root", required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
