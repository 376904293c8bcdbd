#!/usr/bin/env python3
# The control API from outside our C++ client: Python stubs generated from proto/daemon.proto at
# run time drive a real flarelabd through a whole sweep on the simulated rig (check, start, a
# retried start, watch, result, list), a prediction of a planner's scene (Predict, with its
# model handed in, and a path it must refuse), and stop it with SIGTERM. Only the .proto is
# shared with the daemon, so this proves the API, not our client library, is what works.
#
# By hand (Debian's python3-grpcio and python3-grpc-tools, or protoc with grpc_python_plugin):
#
#     python3 tests/daemon/python_client.py --flarelabd build/release/apps/flarelabd \
#         --proto-dir proto --lens data/lenses/heliar-tronnier.csv \
#         --scene tests/data/scenes/report-test.json --model tests/data/models/moving-disc.flm
#
# Exit status 0 when every check holds; 1, with the failed check and the daemon's log, when not.
import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

try:
    import grpc
except ImportError:
    # Debian's python3-grpcio is installed for /usr/bin/python3; a python3 earlier on PATH
    # (pyenv, a virtual environment) may not see it.
    if os.path.realpath(sys.executable) != os.path.realpath("/usr/bin/python3") and os.access(
        "/usr/bin/python3", os.X_OK
    ):
        os.execv("/usr/bin/python3", ["/usr/bin/python3"] + sys.argv)
    sys.exit("python_client.py: no grpc module (install python3-grpcio)")

CLIENT = (("flarelab-client", "python-test"),)
FRAMES = 6  # 0 to 1 degree in steps of 0.2
START_S = 20  # for the daemon to answer
SWEEP_S = 300  # for the whole sweep, fit included
STOP_S = 30  # for the daemon to exit after SIGTERM


class CheckFailed(Exception):
    pass


def check(condition, message):
    if not condition:
        raise CheckFailed(message)


def generateStubs(proto_dir, out_dir):
    """Writes daemon_pb2.py and daemon_pb2_grpc.py into out_dir and imports them."""
    proto = os.path.join(proto_dir, "daemon.proto")
    common = ["-I" + proto_dir, "--python_out=" + out_dir, "--grpc_python_out=" + out_dir, proto]
    # grpc_tools first; Debian 12's (1.14) carries protoc 3.5, which predates proto3 `optional`
    # (SimFaults.head_stall_at_deg), so then the protoc and grpc_python_plugin of the C++ build.
    attempts = [[sys.executable, "-m", "grpc_tools.protoc"] + common]
    protoc, plugin = shutil.which("protoc"), shutil.which("grpc_python_plugin")
    if protoc and plugin:
        attempts.append([protoc, "--plugin=protoc-gen-grpc_python=" + plugin] + common)
    errors = []
    for command in attempts:
        run = subprocess.run(command, capture_output=True, text=True)
        if run.returncode == 0:
            break
        errors.append("%s: %s" % (" ".join(command[:3]), (run.stderr or run.stdout).strip()))
    else:
        raise CheckFailed("cannot generate the Python stubs:\n  " + "\n  ".join(errors))
    sys.path.insert(0, out_dir)
    import daemon_pb2
    import daemon_pb2_grpc

    return daemon_pb2, daemon_pb2_grpc


def waitForDaemon(daemon, socket_path, stub, pb):
    """The rig's description, once the daemon answers on its socket."""
    deadline = time.monotonic() + START_S
    last_error = "no socket"
    while time.monotonic() < deadline:
        check(daemon.poll() is None, "flarelabd exited at start (code %s)" % daemon.returncode)
        if os.path.exists(socket_path):
            try:
                return stub.DescribeRig(pb.DescribeRigRequest(), metadata=CLIENT, timeout=2)
            except grpc.RpcError as e:
                last_error = "%s: %s" % (e.code().name, e.details())
        time.sleep(0.1)
    raise CheckFailed("flarelabd did not answer within %d s (%s)" % (START_S, last_error))


def sweepConfig(pb, lens_path):
    with open(lens_path) as f:
        prescription = f.read()
    lens = pb.SimLens(prescription_csv=prescription, name=os.path.basename(lens_path))
    return pb.SweepConfig(
        sim=pb.SimSettings(lens=lens, fast=True, seed=1),
        from_deg=0.0,
        to_deg=1.0,
        step_deg=0.2,
        exposure_times_s=[0.25, 1.0, 4.0],
        width_px=96,
        height_px=64,
        output_dir="py-sweep",
        previews=True,
        fit=True,
    )


def predictRequest(pb, args, model_path):
    """The scene of --scene with its model named `model_path`, and --model as the file."""
    with open(args.scene) as f:
        scene = json.load(f)
    for camera in scene["cameras"]:
        camera["model"] = model_path
    with open(args.model, "rb") as f:
        model = f.read()
    return pb.PredictRequest(
        scene_json=json.dumps(scene),
        files=[pb.NamedFile(name=os.path.basename(args.model), content=model)],
        scene_name="planner-scene.json",
        options=pb.PredictOptions(table_phi_step_deg=30, return_report_files=True),
    )


def checkPredict(args, pb, stub):
    """A prediction of --scene with --model, its figures held against its report.json."""
    model_name = os.path.basename(args.model)
    response = stub.Predict(predictRequest(pb, args, model_name), metadata=CLIENT, timeout=120)
    report = json.loads(response.report_json)
    names = [c.name for c in response.cameras]
    check(
        names == [c["name"] for c in report["cameras"]] and len(names) > 0,
        "Predict: cameras %s, report.json has %s" % (names, [c["name"] for c in report["cameras"]]),
    )
    check(report["scene"] == "planner-scene.json", "Predict: report.json names the scene %r"
          % report["scene"])
    drawn = 0
    for camera, reported in zip(response.cameras, report["cameras"]):
        check(camera.model == model_name, "Predict: camera %s has model %r" % (camera.name,
                                                                           camera.model))
        for field in ("min", "max", "mean", "log_average", "total"):
            value = getattr(camera.fixed_lights, field)
            check(
                math.isfinite(value) and value == reported["fixed_lights"][field],
                "Predict: camera %s fixed_lights.%s %r, report.json %r"
                % (camera.name, field, value, reported["fixed_lights"][field]),
            )
        if reported["contrast_ratio"] is not None:
            check(
                camera.HasField("contrast_ratio")
                and camera.contrast_ratio == reported["contrast_ratio"],
                "Predict: camera %s contrast_ratio differs from report.json" % camera.name,
            )
        for light, reported_light in zip(camera.lights, reported["lights"]):
            check(
                light.state == reported_light["state"]
                and light.figures.mean == reported_light["figures"]["mean"],
                "Predict: camera %s light %s differs from report.json" % (camera.name, light.name),
            )
            drawn += light.state == "drawn"
        drawn += camera.fixed_lights.mean > 0
    check(drawn > 0, "Predict: no light drawn and no flare at any camera")
    if "switching" in report:
        shots = [(s.camera, s.from_utc, s.to_utc) for s in response.switching.shots]
        expected = [(s["camera"], s["from_utc"], s["to_utc"]) for s in report["switching"]["segments"]]
        check(shots == expected, "Predict: shots %s, report.json %s" % (shots, expected))
    outputs = {f.name for f in response.outputs}
    check(
        {"report.html", "figures.csv"} <= outputs,
        "Predict: outputs %s lack report.html or figures.csv" % sorted(outputs),
    )

    # A scene that names a file outside what it was handed is refused, naming the field.
    for path in ("../" + model_name, os.path.abspath(args.model)):
        try:
            stub.Predict(predictRequest(pb, args, path), metadata=CLIENT, timeout=60)
            raise CheckFailed("Predict: the model path %r was accepted" % path)
        except grpc.RpcError as e:
            check(
                e.code() == grpc.StatusCode.INVALID_ARGUMENT
                and "cameras[0].model" in (e.details() or ""),
                "Predict: model %r gave %s (%s), expected INVALID_ARGUMENT naming cameras[0].model"
                % (path, e.code().name, e.details()),
            )


def runChecks(args, pb, rpc, daemon, socket_path, output_root):
    channel = grpc.insecure_channel("unix:" + socket_path)
    try:
        stub = rpc.FlareLabStub(channel)

        # The rig.
        rig = waitForDaemon(daemon, socket_path, stub, pb)
        check(rig.api_version == 1, "DescribeRig: api_version %d, expected 1" % rig.api_version)
        check(
            rig.output_root == output_root,
            "DescribeRig: output_root %r, expected %r" % (rig.output_root, output_root),
        )

        # A bad configuration is refused, naming the field.
        config = sweepConfig(pb, args.lens)
        bad = pb.SweepConfig()
        bad.CopyFrom(config)
        bad.step_deg = -1
        try:
            stub.CheckSweep(pb.CheckSweepRequest(config=bad), metadata=CLIENT, timeout=30)
            raise CheckFailed("CheckSweep: step_deg = -1 was accepted")
        except grpc.RpcError as e:
            check(
                e.code() == grpc.StatusCode.INVALID_ARGUMENT,
                "CheckSweep: step_deg = -1 gave %s (%s), expected INVALID_ARGUMENT"
                % (e.code().name, e.details()),
            )
            check(
                "config.step_deg" in (e.details() or ""),
                "CheckSweep: message %r does not name config.step_deg" % e.details(),
            )

        # Start, and a retried start with the same request_id: one job.
        start = pb.StartSweepRequest(request_id="py-1", config=config)
        job = stub.StartSweep(start, metadata=CLIENT, timeout=30)
        check(job.id != "", "StartSweep: no job id")
        check(job.client == "python-test", "StartSweep: client %r, expected python-test" % job.client)
        again = stub.StartSweep(start, metadata=CLIENT, timeout=30)
        check(
            again.id == job.id,
            "StartSweep retried with request_id py-1: job %r, expected %r" % (again.id, job.id),
        )

        # Watch it to the end.
        sequences, frames_seen, last = [], set(), None
        for event in stub.WatchJob(
            pb.WatchJobRequest(job_id=job.id), metadata=CLIENT, timeout=SWEEP_S
        ):
            sequences.append(event.sequence)
            if event.kind == pb.FRAME:
                frames_seen.add(event.frame_index)
            last = event
        check(last is not None, "WatchJob: the stream ended without an event")
        check(
            all(a < b for a, b in zip(sequences, sequences[1:])),
            "WatchJob: sequence numbers do not increase: %s" % sequences,
        )
        check(
            frames_seen == set(range(FRAMES)),
            "WatchJob: FRAME events for frames %s, expected 0 to %d"
            % (sorted(frames_seen), FRAMES - 1),
        )
        check(
            last.job.state == pb.SUCCEEDED,
            "WatchJob: the last event's job is %s (%s), expected SUCCEEDED"
            % (pb.JobState.Name(last.job.state), last.job.reason),
        )

        # Its products.
        result = stub.GetJobResult(pb.GetJobResultRequest(job_id=job.id), metadata=CLIENT, timeout=30)
        expected_dir = os.path.join(output_root, "py-sweep")
        check(
            result.sweep_dir == expected_dir,
            "GetJobResult: sweep_dir %r, expected %r" % (result.sweep_dir, expected_dir),
        )
        check(os.path.isfile(result.manifest), "GetJobResult: no manifest %r" % result.manifest)
        with open(result.manifest) as f:
            manifest = json.load(f)
        manifest_frames = manifest.get("frames")
        check(
            isinstance(manifest_frames, list) and len(manifest_frames) == FRAMES,
            "manifest %s: %s frames, expected %d"
            % (result.manifest, len(manifest_frames or []), FRAMES),
        )
        check(
            result.model_file != "" and os.path.getsize(result.model_file) > 0,
            "GetJobResult: model_file %r missing or empty" % result.model_file,
        )
        check(
            len(result.previews) == FRAMES and all(os.path.isfile(p) for p in result.previews),
            "GetJobResult: previews %s, expected %d files" % (list(result.previews), FRAMES),
        )

        listed = stub.ListJobs(pb.ListJobsRequest(), metadata=CLIENT, timeout=30)
        check(
            job.id in [j.id for j in listed.jobs],
            "ListJobs: %s does not list %s" % ([j.id for j in listed.jobs], job.id),
        )

        # A planner's prediction over the same socket.
        checkPredict(args, pb, stub)
    finally:
        channel.close()

    # A clean stop: exit code 0, the socket removed.
    daemon.send_signal(signal.SIGTERM)
    try:
        code = daemon.wait(timeout=STOP_S)
    except subprocess.TimeoutExpired:
        raise CheckFailed("flarelabd still running %d s after SIGTERM" % STOP_S)
    check(code == 0, "flarelabd exited with code %d after SIGTERM, expected 0" % code)
    check(not os.path.exists(socket_path), "flarelabd left its socket %s" % socket_path)


def main():
    parser = argparse.ArgumentParser(description="flarelabd driven over gRPC from Python")
    parser.add_argument("--flarelabd", required=True, help="the daemon binary")
    parser.add_argument("--proto-dir", required=True, help="the repository's proto/ folder")
    parser.add_argument("--lens", required=True, help="a lens CSV, as in data/lenses")
    parser.add_argument("--scene", required=True, help="a scene file to predict (flarelab-scene)")
    parser.add_argument("--model", required=True, help="the model file every camera of it uses")
    args = parser.parse_args()

    # Under /tmp: a Unix socket path must stay under about 100 bytes.
    temp_dir = tempfile.mkdtemp(prefix="flarelab-py-", dir="/tmp")
    state_dir = os.path.join(temp_dir, "state")
    output_root = os.path.join(temp_dir, "out")
    socket_path = os.path.join(state_dir, "flarelabd.sock")
    log_path = os.path.join(temp_dir, "flarelabd.log")
    daemon, log, failed = None, None, True
    began = time.monotonic()
    try:
        check(len(socket_path) < 100, "socket path %s is too long" % socket_path)
        stub_dir = os.path.join(temp_dir, "stubs")
        os.mkdir(stub_dir)
        pb, rpc = generateStubs(args.proto_dir, stub_dir)

        os.mkdir(output_root)
        log = open(log_path, "w")
        daemon = subprocess.Popen(
            [args.flarelabd, "--state-dir", state_dir, "--output-root", output_root],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        runChecks(args, pb, rpc, daemon, socket_path, os.path.realpath(output_root))
        failed = False
        print(
            "python_client: a whole sweep and a prediction over the API in %.1f s"
            % (time.monotonic() - began)
        )
    except CheckFailed as e:
        print("python_client: FAILED: %s" % e, file=sys.stderr)
    except grpc.RpcError as e:
        print("python_client: FAILED: %s: %s" % (e.code().name, e.details()), file=sys.stderr)
    except Exception as e:  # a broken file, a missing binary: still a failure, with the log
        print("python_client: FAILED: %s: %s" % (type(e).__name__, e), file=sys.stderr)
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
            daemon.wait()
        if log is not None:
            log.close()
        if failed and daemon is not None:
            with open(log_path) as f:
                print("---- flarelabd log ----\n" + f.read() + "----", file=sys.stderr)
        shutil.rmtree(temp_dir, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
