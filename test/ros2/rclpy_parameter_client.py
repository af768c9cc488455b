"""Run by the ros2 tier under a real Jazzy: rclpy's AsyncParameterClient against a node.

argv[1]: the node's fully qualified name. Lists, gets, sets (one good value, one of the wrong
type, one undeclared name), describes and gets the types of its parameters; prints one JSON
object of what came back.
"""
import json
import sys

import rclpy
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient


def main():
    rclpy.init()
    node = rclpy.create_node('parameter_client_probe')
    client = AsyncParameterClient(node, sys.argv[1])
    if not client.wait_for_services(timeout_sec=30.0):
        print(json.dumps({'error': 'parameter services not available'}))
        return

    def answer(future):
        rclpy.spin_until_future_complete(node, future, timeout_sec=30.0)
        if not future.done():
            raise SystemExit('no reply within 30 s')
        return future.result()

    found = {}
    found['list'] = sorted(answer(client.list_parameters()).result.names)
    found['get'] = [[v.type, v.double_value, v.string_value]
                    for v in answer(client.get_parameters(['alpha', 'system'])).values]
    found['get_undeclared'] = len(answer(client.get_parameters(['alpha', 'no_such'])).values)
    results = answer(client.set_parameters([
        Parameter('alpha', value=3.0), Parameter('alpha', value='fast'),
        Parameter('no_such', value=1)])).results
    found['set'] = [[r.successful, r.reason] for r in results]
    found['get_after_set'] = answer(client.get_parameters(['alpha'])).values[0].double_value
    found['describe'] = [[d.name, d.type] for d in
                         answer(client.describe_parameters(['alpha', 'system'])).descriptors]
    found['types'] = list(answer(client.get_parameter_types(['alpha', 'system'])).types)
    print(json.dumps(found))
    node.destroy_node()
    rclpy.shutdown()


main()
