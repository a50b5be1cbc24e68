"""python -m service.scenarios schema > docs/scenario.schema.json"""

import json
import sys

from service.scenarios.model import json_schema, preset_names

if len(sys.argv) > 1 and sys.argv[1] == "schema":
    print(json.dumps(json_schema(), indent=2))
else:
    print("\n".join(preset_names()))
