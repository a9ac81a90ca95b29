"""The HTTP API's routes, one router per resource (the table of roadgrip/cloud/api/app.py says which route is where);
create_app includes them. Each route parses (FastAPI, pydantic, the parsers of the payloads), authorizes
(roadgrip/cloud/api/deps.py), calls the backend (roadgrip/cloud/api/backend.py) and answers; errors go to the one
handler of roadgrip/cloud/api/errors.py."""
