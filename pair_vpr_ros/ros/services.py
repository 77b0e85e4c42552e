"""The node's services (set_localization and the map services), its `/diagnostics` and its
autosave timer. A mixin of `VprNode` (ros/node.py); the map work itself is `MapControl`'s."""

from __future__ import annotations

import json

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool, Trigger

from pair_vpr_ros import params
from pair_vpr_ros.ros.outputs import publish_while_up
from pair_vpr_ros.ros.runtime import diagnostic_values


class NodeServices:
    """Services, diagnostics and autosave of `VprNode` (it supplies `values`, `maps`, `stats`,
    `frames`, `outputs`, `pub_diag`, `identity`, `fleet` and `_prior_summary`)."""

    def _make_services(self, v: dict) -> None:
        services = MutuallyExclusiveCallbackGroup()
        for srv_type, name, handler in (
            (SetBool, "~/set_localization", self._srv_localization),
            (Trigger, "~/save_map", self._trigger(lambda: self.maps.save(self.values["map_dir"]))),
            (Trigger, "~/load_map", self._trigger(lambda: self.maps.load(self.values["map_dir"]))),
            (Trigger, "~/clear_map", self._trigger(self._clear)),
            (Trigger, "~/build_map", self._trigger(self._start_build)),
            (Trigger, "~/map_info", self._trigger(self._map_info)),
        ):
            self.create_service(srv_type, name, handler, callback_group=services)
        diagnostics = MutuallyExclusiveCallbackGroup()
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics, diagnostics)
        if v["autosave_period"] > 0:
            self.create_timer(v["autosave_period"], self._autosave, services)

    # ---- diagnostics, autosave, services --------------------------------------------------------
    def diagnostic_values(self) -> dict[str, str]:
        """Everything `/diagnostics` reports, as strings."""
        out = diagnostic_values(self.values, self.stats, self.frames, self.maps)
        return {**out, **self.rig_diagnostics()}

    def _publish_diagnostics(self) -> None:
        values = self.diagnostic_values()
        problems = self.stats.problems()
        level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        if self.maps.build.error:  # until the next successful build
            level, problems = (
                DiagnosticStatus.ERROR,
                "; ".join(x for x in (self.maps.build.error, problems) if x),
            )
        status = DiagnosticStatus(
            name="vpr_node: loop closure",
            hardware_id=self.values["device"],
            level=level,
            message=problems or f"{values['mode']}, {values['map_size']} keyframes",
            values=[KeyValue(key=k, value=x) for k, x in values.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        publish_while_up(self, self.pub_diag, msg)

    def _autosave(self) -> None:
        result = self.maps.autosave(self.values["map_dir"])
        if result is not None:
            self._log("info" if result[0] else "error", f"autosave: {result[1]}")

    @staticmethod
    def _trigger(action):
        def handle(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            response.success, response.message = action()
            return response

        return handle

    def _srv_localization(self, request: SetBool.Request, response: SetBool.Response):
        mode = "localization" if request.data else "mapping"
        result = self.set_parameters([Parameter("mode", value=mode)])[0]
        response.success = result.successful
        response.message = f"mode: {mode}" if result.successful else result.reason
        return response

    def _map_info(self) -> tuple[bool, str]:
        """The live map and the last build as JSON (a script polls this after build_map)."""
        info = {
            "keyframes": self.maps.size(),
            "mode": self.maps.state.mode,
            "map_dir": self.values["map_dir"],
            "build": self.maps.build.to_dict(),
            "robot": self.identity.robot,
            "session": self.identity.session,
            "prior_maps": self._prior_summary,  # dir, keyframes, sessions (fixed at start-up)
        }
        if self.fleet is not None:
            info["fleet"] = self.fleet.state()
        return True, json.dumps(info)

    def _clear(self) -> tuple[bool, str]:
        result = self.maps.clear()
        self.outputs.clear_markers()
        return result

    def _start_build(self) -> tuple[bool, str]:
        v = self.values
        return self.maps.start_build(
            v["build_source"],
            v["map_dir"],
            params.detector_config(v),
            image_topic=v["build_image_topic"] or None,
            image_period=v["build_image_period"],
            index=params.index_config(v),
            max_pixels=v["max_image_pixels"],
            geometry=params.geometry_config(v),
            identity=self.identity,
        )
